"""Answers the analysis keeps for the same question asked again: one bounded store, the
newest kept, safe between threads (a live view measures in a thread of its own).

A run's measurement asks for the same model's closed loop, impulse responses and poles
many times over (its responses, fits and latency search): :func:`hapsim.analysis.network.
closed_loop`, :mod:`hapsim.analysis.error_response`,
:func:`hapsim.analysis.loop_poles.roots_w` and
:func:`hapsim.analysis.subsample.split_hold_body` keep them here.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

__all__ = ["Kept"]


class Kept:
    """A bounded store of computed answers by key, the least recently asked dropped first.

    Parameters
    ----------
    size : int >= 1
        Answers kept.

    Notes
    -----
    A key may name an object by its identity (``id(obj)``): :meth:`get`'s ``owner`` is
    then stored beside the answer, so that id is not reused while the answer is kept,
    and an answer is given only to the same object. The answer is shared: the caller
    copies it or hands out a read-only array.
    """

    def __init__(self, size: int) -> None:
        self.size = int(size)
        self._kept: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key, compute, owner=None):
        """The answer kept for ``key`` (and ``owner``), else ``compute()``, kept.

        Parameters
        ----------
        key : hashable
            The question.
        compute : callable
            ``compute() -> answer``; what it raises is raised, nothing kept.
        owner : object, optional
            The object ``key`` names by identity (Notes).

        Returns
        -------
        object
            The answer, shared with every caller of the same key.
        """
        with self._lock:
            hit = self._kept.get(key)
            if hit is not None and hit[0] is owner:
                self._kept.move_to_end(key)
                return hit[1]
        answer = compute()
        with self._lock:
            self._kept[key] = (owner, answer)
            while len(self._kept) > self.size:
                self._kept.popitem(last=False)
        return answer
