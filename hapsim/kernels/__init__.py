"""numba kernels of the mass-interaction engine.

Plain arrays and floats only; nothing here imports from the API layer (``hapsim.engine``,
``hapsim.scene``), and the API layer validates everything before calling in
(docs/design.md, rule 3). Units are SI throughout.
"""
