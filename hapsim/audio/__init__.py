"""Sound of a scene: offline rendering to WAV, live output through JACK, OSC control.

The multi-rate model itself is the engine's (:class:`hapsim.engine.Engine` with a scene's
``audio`` section, :mod:`hapsim.kernels.audio`); this package feeds it gestures and moves
its frames to files and sound servers.
"""
