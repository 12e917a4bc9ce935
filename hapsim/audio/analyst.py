"""The background analysis of live control: the stability check of a change, run in a
child process (:class:`Analyst`), so that no BLAS thread and no Python work of the check
shares the sample loop's process."""

from __future__ import annotations

from hapsim.errors import HapsimError

__all__ = ["Analyst"]


class Analyst:
    """Where a :class:`Controller` runs its heavy analysis: a child process, or here.

    The child (a ``spawn`` :class:`multiprocessing.pool.Pool` of one worker, ``SCHED_OTHER``
    at nice 10, its stdout sent to stderr so nothing lands in a ``--json`` report) is
    started at once and kept; a call waits for its answer without holding the GIL, so the
    haptic loop and the sound callback of this process keep running. :meth:`close`
    terminates it, work under way included.

    Parameters
    ----------
    background : bool
        Use a child process (False: call in the calling thread).
    timeout_s : float
        Longest wait of :meth:`call` [s]; then :class:`hapsim.errors.HapsimError`.
    """

    def __init__(self, background: bool = True, timeout_s: float = 120.0) -> None:
        self._pool = None
        self.timeout_s = float(timeout_s)
        if background:
            import multiprocessing
            self._pool = multiprocessing.get_context("spawn").Pool(1, initializer=_background)

    @property
    def background(self) -> bool:
        """Whether calls go to the child process (False: in the calling thread, or
        after :meth:`close`)."""
        return self._pool is not None

    def submit(self, fn, args: tuple, done=None):
        """Start ``fn(*args)``; ``done(result)`` when it ends (``done({"error": ...})`` if
        it raised). Returns a handle with ``ready()`` and ``wait(timeout)``.

        Parameters
        ----------
        fn : callable
            A module-level function (the child receives it pickled).
        args : tuple
            Its arguments (picklable).
        done : callable, optional
            Called with the result, or with ``{"error": "Type: message"}``; in the child's
            case from the pool's result thread.

        Returns
        -------
        multiprocessing.pool.AsyncResult or _Done
            The handle; in-process, the work is finished (and ``done`` called) on return.
        """
        def failed(exc):
            if done is not None:
                done({"error": f"{type(exc).__name__}: {exc}"})

        if self._pool is not None:
            return self._pool.apply_async(fn, args, callback=done, error_callback=failed)
        h = _Done()
        try:
            res = fn(*args)
        except Exception as exc:
            failed(exc)
            return h
        if done is not None:
            done(res)
        return h

    def call(self, fn, *args):
        """``fn(*args)``, in the child when there is one (its exception re-raised).

        Parameters
        ----------
        fn : callable
            A module-level function (pickled for the child).
        *args
            Its arguments.

        Returns
        -------
        object
            What ``fn`` returned.

        Raises
        ------
        HapsimError
            No answer within :attr:`timeout_s`.
        """
        if self._pool is None:
            return fn(*args)
        import multiprocessing
        try:
            return self._pool.apply_async(fn, args).get(self.timeout_s)
        except multiprocessing.TimeoutError:
            raise HapsimError(f"the analysis took longer than {self.timeout_s:g} s") from None

    def close(self) -> None:
        """Terminate the child (work under way is dropped)."""
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None


class _Done:
    """The handle of work done in-process (already finished)."""

    def ready(self) -> bool:
        return True

    def wait(self, timeout=None) -> None:
        return None


def _background() -> None:
    """Analysis process initialiser: normal scheduling, low priority (it must never
    compete with the haptic loop or the sound callback that started it)."""
    import os
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass
    try:
        os.nice(10)
    except (AttributeError, OSError):
        pass
    try:
        os.dup2(2, 1)         # LAPACK and friends print on fd 1: keep it off the report
    except OSError:
        pass
    from hapsim.blas import limit_blas_threads
    limit_blas_threads(1)
    import hapsim.analysis.identify  # noqa: F401  (loaded before the first window counts)
