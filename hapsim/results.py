"""The base of the API's typed results (:mod:`hapsim.api`, :mod:`hapsim.api`): a frozen
dataclass whose fields are a command's ``--json`` keys."""

from __future__ import annotations

import dataclasses

__all__ = ["Report"]


class Report:
    """The common part of the results: built from, and turned back into, a ``--json``
    object. Fields named in ``_OPTIONAL`` are left out of :meth:`to_dict` when None (the
    command prints them only when asked). A key of the command's report that has no field
    yet is kept in :attr:`extra` (and in :meth:`to_dict`), so the result never loses what
    the command says; the tests keep the fields and the keys equal."""

    _OPTIONAL: tuple = ()

    def to_dict(self) -> dict:
        """The command's ``--json`` object.

        Returns
        -------
        dict
            One entry per field, in field order (optional ones only when set), then
            :attr:`extra`.
        """
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if not (f.name in self._OPTIONAL and getattr(self, f.name) is None)}
        out.update(self.extra)
        return out

    @property
    def extra(self) -> dict:
        """Keys of the command's report without a field here (empty when in step)."""
        return getattr(self, "_extra", {})

    def replace(self, **changes):
        """A copy with some fields changed, keeping what the result carries beside its
        fields (:attr:`extra`, ``exit_code``, the analysis behind it), which
        :func:`dataclasses.replace` would drop.

        Parameters
        ----------
        **changes
            Field names and their new values.

        Returns
        -------
        Report
            A new instance of the same class.

        Raises
        ------
        TypeError
            A name that is not a field.
        """
        new = dataclasses.replace(self, **changes)
        names = {f.name for f in dataclasses.fields(self)}
        for k, v in vars(self).items():
            if k not in names:
                object.__setattr__(new, k, v)
        return new

    @classmethod
    def from_dict(cls, d: dict, **attrs):
        """A result from a command's ``--json`` object (the inverse of :meth:`to_dict`).

        Parameters
        ----------
        d : dict
            The object: each field's key (a missing one is None); the other keys are
            kept in :attr:`extra`.
        **attrs
            Objects the result carries beside its fields (the analysis behind it, a fit,
            the record), set as attributes.

        Returns
        -------
        Report
            An instance of the class it is called on.

        Raises
        ------
        ConfigError
            ``d`` is no mapping (keyed ``d``; before: an AttributeError).
        """
        if not isinstance(d, dict):
            from hapsim.errors import ConfigError
            raise ConfigError(f"must be a report's JSON object (a dict), got {d!r}", key="d")
        names = {f.name for f in dataclasses.fields(cls)}
        obj = cls(**{n: d.get(n) for n in names})
        object.__setattr__(obj, "_extra", {k: v for k, v in d.items() if k not in names})
        for k, v in attrs.items():
            object.__setattr__(obj, k, v)
        return obj
