"""JACK process callbacks that never enter Python: numba cfuncs over hapsim's arrays.

JACK-Client's process callback is a Python function: every block, the server's real-time
thread takes the GIL, runs a few Python lines and calls the compiled model. Whenever another
thread of the process holds the GIL (the haptic loop, the OSC server, the telemetry writer,
the garbage collector) the callback waits for it, and a wait of one block (5.3 ms at
256 frames, 48 kHz) is an xrun. The callback here is C-callable machine code compiled by
numba (:func:`numba.cfunc`): it reads a table of addresses (this module's *context*, an
``int64`` array handed to JACK as the callback's ``void *arg``), views LiveSound's arrays
through :func:`numba.carray`, calls :func:`hapsim.kernels.audio.run_frames` and copies each
channel into the port buffer ``jack_port_get_buffer`` returns. No Python object is touched
and the GIL is never taken, so nothing that the rest of the process does in Python can
delay a block (JACK API: ``jack_set_process_callback``; the buffer pointer must be fetched
in every cycle, ``jack_port_get_buffer``).

:func:`process` runs a :class:`~hapsim.audio.live.LiveSound`'s model (``hapsim play``);
:func:`process_ring` copies the frames of a :class:`~hapsim.audio.live.FrameRing` that the
haptic loop fills (``hapsim run --sound``), through
:func:`hapsim.kernels.audio.ring_read`. Context layout (:data:`CTX`): the scalars ``nsub``, ``linear``, ``last``, ``port``, the
channel count, the block capacity (rows of ``audio``), a callback counter, a counter of
blocks larger than the capacity (silence out), then the addresses and sizes of the arrays
in :func:`run_frames`'s order, and the JACK port pointers (one per channel, at most
:data:`MAX_CHANNELS`), then a log of the callbacks whose block had starved frames (its
length, then at most :data:`LOG_MAX` callback numbers). For a FrameRing the array slots hold the ring's address and rows
and the addresses of its write count and read state.
"""

from __future__ import annotations

import ctypes
import ctypes.util

import numba as nb
import numpy as np
from numba import types
from numba.extending import register_jitable

from hapsim.kernels import audio as audio_kernel
from hapsim.kernels.pointers import voidptr
from hapsim.kernels.sources import cache_ok

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`): the
#: multi-rate kernel and the engine helpers it inlines.
COMPILED_SOURCES = ("hapsim/kernels/audio.py", "hapsim/kernels/cordis.py",
                    "hapsim/kernels/pointers.py")
#: Their SHA-256: numba keys its disk cache on this file alone, so this literal changes
#: with them (``tests/test_compiled_loop_sources.py`` says so); until then, no cache.
COMPILED_SOURCES_SHA256 = "bc30491215471487b980571fcd37cd227dcee4f46320cfbedc121f920a86ec09"
#: Whether numba's disk cache may serve this module's compiled code.
CACHE_OK = cache_ok(COMPILED_SOURCES, COMPILED_SOURCES_SHA256)

__all__ = ["NativeProcess", "native_available", "client_rt_priority", "process", "process_ring",
           "MAX_CHANNELS", "CTX", "LOG_MAX"]

#: Channels (JACK output ports) the native callback serves.
MAX_CHANNELS = 16

# run_frames' array arguments after ``port`` (LiveSound.callback_pack.arrays), with their
# dtype: (ring, wr, st, fring), then the engine's multi-rate state
# (Engine.multirate_pack.args without the trailing inv_ta).
_F8, _I8 = 0, 1
_ARRAYS = (_F8, _I8, _F8, _F8,                      # ring, wr, st, fring
           _F8, _F8, _F8, _I8, _F8, _I8,            # x, xp, f, mobile, t2m, fixed
           _I8, _I8, _F8, _F8,                      # sd_i1, sd_i2, sd_k, sd_z
           _I8, _I8, _F8, _F8, _F8,                 # c_i1, c_i2, c_k, c_z, c_thr
           _I8, _I8, _F8)                           # l_idx, l_code, l_gain
_NA = len(_ARRAYS)
#: Context indices.
CTX = {"nsub": 0, "linear": 1, "last": 2, "port": 3, "channels": 4, "rows": 5,
       "calls": 6, "too_big": 7, "inv_ta": 8, "audio": 9, "arrays": 10,
       "ports": 10 + 2 * _NA}
#: Callbacks whose block had starved frames, logged (the first ones; see NativeProcess).
LOG_MAX = 256
CTX["log_n"] = CTX["ports"] + MAX_CHANNELS
CTX["log"] = CTX["log_n"] + 1
_CTX_N = CTX["log"] + LOG_MAX


def _load_libjack() -> None:
    """Make libjack's symbols visible to numba's linker (``jack_port_get_buffer`` is an
    external function of the compiled callback, resolved when it is compiled or loaded
    from numba's cache)."""
    import jack
    import llvmlite.binding as llvm

    path = ctypes.util.find_library("jack") or jack._libname
    llvm.load_library_permanently(path)


_load_libjack()
CTX_PORTS = CTX["ports"]
_A = CTX["arrays"]
_RING = CTX["arrays"]          # FrameRing: ring address, rows, wr address, st address
_LOG_N, _LOG = CTX["log_n"], CTX["log"]
_get_buffer = types.ExternalFunction("jack_port_get_buffer",
                                     types.voidptr(types.voidptr, types.uint32))


# The context's accessors: overloads compiled once per signature and called (LLVM inlines
# them), not inlined into numba's IR at each of the 24 call sites (which translated and
# typed the accessor again at every site). A view, no arithmetic.
@register_jitable
def _f8(c, i):
    return nb.carray(voidptr(c[_A + 2 * i]), (c[_A + 2 * i + 1],), np.float64)


@register_jitable
def _i8(c, i):
    return nb.carray(voidptr(c[_A + 2 * i]), (c[_A + 2 * i + 1],), np.int64)


@nb.njit(inline="always", cache=CACHE_OK)
def _to_ports(c, nframes, audio, silence):
    """Write ``audio[:nframes]`` (or silence) to each channel's JACK port buffer."""
    n = np.int64(nframes)
    for ch in range(c[4]):
        out = nb.carray(_get_buffer(voidptr(c[CTX_PORTS + ch]), nframes), (n,), np.float32)
        for r in range(n):
            out[r] = 0.0 if silence else audio[r, ch]


@nb.njit(inline="always", cache=CACHE_OK)
def _enter(arg, nframes):
    """A callback's start: the context, the block as an int, the frames buffer, and
    whether the block fits it (if not: silence written and counted, nothing else to do)."""
    c = nb.carray(arg, (_CTX_N,), np.int64)
    c[6] += 1
    n = np.int64(nframes)
    audio = nb.carray(voidptr(c[9]), (c[5], c[4]), np.float32)
    if n > c[5]:                       # a block larger than the buffers: silence
        c[7] += 1
        _to_ports(c, nframes, audio, True)
        return c, n, audio, False
    return c, n, audio, True


@nb.cfunc(types.int32(types.uint32, types.voidptr), nopython=True, cache=CACHE_OK)
def process(nframes, arg):
    """The JACK process callback (``JackProcessCallback``): ``arg`` is the context.

    Parameters
    ----------
    nframes : uint32
        Frames JACK asks for this cycle.
    arg : void *
        Address of the context, an int64 array of :data:`CTX`'s layout (kept alive by
        :class:`NativeProcess`).

    Returns
    -------
    int32
        0 (JACK's "continue"); a block larger than the buffers is silence, counted.
    """
    c, n, audio, fits = _enter(arg, nframes)
    if not fits:
        return 0
    inv_ta = nb.carray(voidptr(c[8]), (1,), np.float64)[0]
    st = _f8(c, 2)
    starved0 = st[2]
    audio_kernel.run_frames(n, c[0], c[1] != 0, c[2] != 0, c[3],
                            _f8(c, 0), _i8(c, 1), st, _f8(c, 3),
                            _f8(c, 4), _f8(c, 5), _f8(c, 6), _i8(c, 7), _f8(c, 8), _i8(c, 9),
                            _i8(c, 10), _i8(c, 11), _f8(c, 12), _f8(c, 13),
                            _i8(c, 14), _i8(c, 15), _f8(c, 16), _f8(c, 17), _f8(c, 18),
                            _i8(c, 19), _i8(c, 20), _f8(c, 21), inv_ta, audio)
    if st[2] > starved0 and c[_LOG_N] < LOG_MAX:      # a block with starved frames
        c[_LOG + c[_LOG_N]] = c[6]
        c[_LOG_N] += 1
    _to_ports(c, nframes, audio, False)
    return 0


@nb.cfunc(types.int32(types.uint32, types.voidptr), nopython=True, cache=CACHE_OK)
def process_ring(nframes, arg):
    """The JACK process callback over a :class:`~hapsim.audio.live.FrameRing` (``hapsim run
    --sound``): :func:`hapsim.kernels.audio.ring_read`, then one copy per channel.

    Parameters
    ----------
    nframes : uint32
        Frames JACK asks for this cycle.
    arg : void *
        Address of the context, an int64 array of :data:`CTX`'s layout (kept alive by
        :class:`NativeProcess`).

    Returns
    -------
    int32
        0 (JACK's "continue"); a block larger than the buffers is silence, counted.
    """
    c, n, audio, fits = _enter(arg, nframes)
    if not fits:
        return 0
    ring = nb.carray(voidptr(c[_RING]), (c[_RING + 1], c[4]), np.float32)
    wr = nb.carray(voidptr(c[_RING + 2]), (1,), np.int64)
    st = nb.carray(voidptr(c[_RING + 3]), (3,), np.int64)
    audio_kernel.ring_read(n, ring, wr, st, audio)
    _to_ports(c, nframes, audio, False)
    return 0




def native_available(live) -> str | None:
    """Why ``live`` cannot use the native callback (None when it can).

    Parameters
    ----------
    live : object
        What a :class:`hapsim.audio.live.JackOutput` plays.

    Returns
    -------
    str or None
        The reason (not a :class:`~hapsim.audio.live.LiveSound`, an array of another dtype
        than the callback was compiled for, too many channels), or None.
    """
    from hapsim.audio.sources import FrameRing, LiveSound

    if isinstance(live, FrameRing):
        pk = live.callback_pack
        ok = (pk.ring.dtype == np.float32 and pk.ring.flags.c_contiguous
              and pk.wr.dtype == np.int64 and pk.st.dtype == np.int64
              and pk.st.size == 3 and pk.block.dtype == np.float32
              and pk.block.flags.c_contiguous)
        if not ok:
            return "a ring array of another dtype or layout than the callback's"
        if len(live.channels) > MAX_CHANNELS:
            return f"{len(live.channels)} channels (at most {MAX_CHANNELS})"
        return None
    if not isinstance(live, LiveSound):
        return f"{type(live).__name__} renders in Python"
    pk = live.callback_pack
    if len(pk.arrays) != _NA:
        return f"{len(pk.arrays)} state arrays, the callback takes {_NA}"
    for a, kind in zip(pk.arrays, _ARRAYS):
        want = np.float64 if kind == _F8 else np.int64
        if not (isinstance(a, np.ndarray) and a.dtype == want and a.ndim == 1
                and a.flags.c_contiguous):
            return "a state array of another dtype or layout than the callback's"
    if pk.block.dtype != np.float32 or not pk.block.flags.c_contiguous:
        return "the block is not C-contiguous float32"
    if len(live.channels) > MAX_CHANNELS:
        return f"{len(live.channels)} channels (at most {MAX_CHANNELS})"
    return None


class NativeProcess:
    """The native process callback of one JACK client over a LiveSound or a FrameRing.

    Parameters
    ----------
    live : hapsim.audio.live.LiveSound or hapsim.audio.live.FrameRing
        What it renders (its arrays are read and written in place, from JACK's thread):
        :func:`process` runs a LiveSound's model, :func:`process_ring` copies a
        FrameRing's frames.
    port_ptrs : sequence of int
        ``jack_port_t *`` of the output ports, one per channel, as integers.

    Attributes
    ----------
    ctx : ndarray of int64, shape (N,)
        The context (see the module's docstring); ``ctx[CTX["calls"]]`` counts callbacks.
    address : int
        The callback's address (``int (*)(jack_nframes_t, void *)``).

    Raises
    ------
    ValueError
        ``live`` cannot use it (:func:`native_available` says why).
    """

    def __init__(self, live, port_ptrs) -> None:
        why = native_available(live)
        if why is not None:
            raise ValueError(why)
        self.live = live
        from hapsim.audio.sources import FrameRing

        if isinstance(live, FrameRing):
            pk = live.callback_pack
            c = np.zeros(_CTX_N, dtype=np.int64)
            c[CTX["channels"]] = len(live.channels)
            c[CTX["rows"]] = pk.block.shape[0]
            c[CTX["audio"]] = pk.block.ctypes.data
            c[_RING], c[_RING + 1] = pk.ring.ctypes.data, pk.ring.shape[0]
            c[_RING + 2], c[_RING + 3] = pk.wr.ctypes.data, pk.st.ctypes.data
            for i, p in enumerate(port_ptrs):
                c[CTX_PORTS + i] = int(p)
            self._keep = tuple(pk)
            self.ctx, self.cfunc, self.address = c, process_ring, process_ring.address
            return
        pk = live.callback_pack
        (nsub, lin, last, port) = pk.head
        self._inv_ta = np.array([float(pk.inv_ta)])
        self._keep = pk.arrays + (pk.block, self._inv_ta)
        c = np.zeros(_CTX_N, dtype=np.int64)
        c[CTX["nsub"]], c[CTX["linear"]], c[CTX["last"]], c[CTX["port"]] = \
            int(nsub), int(bool(lin)), int(bool(last)), int(port)
        c[CTX["channels"]] = len(live.channels)
        c[CTX["rows"]] = pk.block.shape[0]
        c[CTX["inv_ta"]] = self._inv_ta.ctypes.data
        c[CTX["audio"]] = pk.block.ctypes.data
        for i, a in enumerate(pk.arrays):
            c[CTX["arrays"] + 2 * i] = a.ctypes.data
            c[CTX["arrays"] + 2 * i + 1] = a.size
        for i, p in enumerate(port_ptrs):
            c[CTX_PORTS + i] = int(p)
        self.ctx = c
        self.cfunc = process
        self.address = process.address

    @property
    def calls(self) -> int:
        """Callbacks run so far."""
        return int(self.ctx[CTX["calls"]])

    @property
    def starved_calls(self) -> list:
        """Which callbacks (1 = the first) had starved frames, the first :data:`LOG_MAX`
        (a LiveSound: its next period's position had not arrived)."""
        return [int(v) for v in self.ctx[_LOG:_LOG + self.ctx[_LOG_N]]]

    @property
    def too_big(self) -> int:
        """Blocks larger than the buffers (played as silence)."""
        return int(self.ctx[CTX["too_big"]])


def client_rt_priority(client) -> int:
    """The real-time priority of a JACK client's process thread (0 when not real-time).

    Parameters
    ----------
    client : jack.Client

    Returns
    -------
    int
        ``jack_client_real_time_priority`` (JACK API), 0 when it returns -1.
    """
    import jack
    lib = ctypes.CDLL(jack._libname)
    f = lib.jack_client_real_time_priority
    f.argtypes = [ctypes.c_void_p]
    f.restype = ctypes.c_int
    p = f(int(jack._ffi.cast("uintptr_t", client._ptr)))
    return max(0, int(p))
