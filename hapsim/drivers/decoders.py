"""The frame decoders a driver's host side reads its board's replies with: fixed-length
frames found without a start byte (:class:`AlignedDecoder`), and their values mapped to
the axis position (:class:`MappedDecoder`). Part of the drivers' interface
(:mod:`hapsim.drivers.base`)."""

from __future__ import annotations

__all__ = ["AlignedDecoder", "MappedDecoder", "MARK"]

#: What :meth:`AlignedDecoder.feed_into` gives for a one-byte answer its :attr:`marks`
#: name, found where a frame would start (a host's marker write's answer: the 2DIY's
#: realigning probe, :mod:`hapsim.pipeline.haply2_realign`).
MARK = "mark"


class AlignedDecoder:
    """Fixed-length frames without a start byte: a frame is taken where ``parse`` accepts
    it (its fixed bytes match, its values are plausible), else one byte is dropped and
    the next position tried.

    Subclasses set ``length`` and define ``parse(buf) -> value or None`` (``buf`` holds at
    least ``length`` bytes); they may override the hooks :meth:`on_skip` (after each byte
    dropped) and :meth:`accept` (a parsed frame kept or dropped, e.g. implausible).

    Without a start byte or a checksum, a window can parse that is no frame: a lost byte
    leaves the tail of one frame and the head of the next, and where the next frame's
    fixed byte is lost too, or a value byte equals it when realigning, the window's values
    can be plausible (the Hapkit sketch's 9-byte reply: about one lost reply byte in 200
    made such a frame, taken as a fresh reading: a 4.5 mm error on one row, the measured
    k 7 % off, "differs"). With :attr:`confirm_next`, a window is a frame only where the
    stream goes on in its framing: the byte after it, when one has come, must be one a
    frame starts with (:meth:`starts_frame`), and after a realignment the window waits
    for that byte. A window that fails is dropped a byte at a time as any other
    (``unconfirmed``). A lost byte then costs the frames around it (one held until the
    next comes), never a false one.

    A host may also ask for one-byte answers (:attr:`marks`, empty by default): where a
    frame would start (no byte dropped since the last frame) and :meth:`mark_at` says so,
    the byte is given as :data:`MARK`, in its place among the frames, and not counted as
    dropped.

    Attributes
    ----------
    stats : dict
        ``frames`` (taken), ``skipped`` (bytes dropped realigning), ``marks`` (one-byte
        answers given as :data:`MARK`, once there is one); with :attr:`confirm_next`, ``unconfirmed``
        (windows that parsed but the byte after them starts no frame: dropped).
    marks : tuple of int
        The one-byte answers looked for (empty: none).
    """

    length = 1
    #: A window is a frame only where the byte after it starts one (class notes); False:
    #: at once (a protocol whose frames carry their own evidence).
    confirm_next = False

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats = {"frames": 0, "skipped": 0}
        self.marks = ()
        if self.confirm_next:
            self.stats["unconfirmed"] = 0
        self._realigning = False        # bytes dropped since the last frame taken

    def parse(self, buf):
        """The protocol's framing (each driver's decoder): the value of the frame at the
        start of ``buf``, or None where no frame starts there, as its subclass defines it
        (:meth:`feed_into` drops the frame's :attr:`length` bytes, or one byte on None).

        Parameters
        ----------
        buf : bytearray
            The bytes held, at least :attr:`length` of them; not changed.

        Returns
        -------
        object or None
            The frame's value (a subclass's: a float, a tuple), or None: no frame.

        Raises
        ------
        NotImplementedError
            Here: a decoder gives its own.
        """
        raise NotImplementedError

    def unframed(self) -> bool:
        """Whether bytes read since the last frame taken have made none yet: held (a
        frame's start, or bytes not tried yet) or dropped realigning. The evidence, before
        any desync is counted, that a device may have lost its place (a host's watchdog is
        told so: :meth:`hapsim.drivers.torque_watchdog.TorqueWatchdog.suspect`); a frame
        split across two reads is held too, until its rest comes.

        Returns
        -------
        bool
        """
        return bool(self._buf) or self._realigning

    def starts_frame(self, byte: int) -> bool:
        """Whether a frame can start with ``byte`` (:attr:`confirm_next`: the byte after a
        window; by default any).

        Parameters
        ----------
        byte : int
            A byte's value, 0-255.

        Returns
        -------
        bool
            True by default.
        """
        return True

    def on_skip(self) -> None:
        """Called after each byte dropped realigning (``stats["skipped"]`` counted)."""

    def mark_at(self, buf) -> bool:
        """Whether ``buf`` (at least one byte, where a frame would start) begins with a
        one-byte answer of :attr:`marks` (by default: its first byte is one, and the
        byte after it, when one has come, starts a frame or another such answer).

        Parameters
        ----------
        buf : bytearray

        Returns
        -------
        bool
        """
        return buf[0] in self.marks and (
            len(buf) == 1 or buf[1] in self.marks or self.starts_frame(buf[1]))

    def accept(self, value) -> bool:
        """Whether a parsed frame (its ``length`` bytes consumed) is taken; only taken
        frames are returned and counted in ``stats["frames"]``.

        Parameters
        ----------
        value : object
            The frame's value, as :meth:`parse` returned it (not None).

        Returns
        -------
        bool
            True by default.
        """
        return True

    def clear(self) -> None:
        """Drop the bytes held (the start of a frame not complete yet): a re-arming
        drains the link, and what came before it is no part of what follows."""
        del self._buf[:]

    def reset_prediction(self, jumps: int = 1) -> None:
        """Forget what earlier frames say the next one should be (a decoder that checks
        a frame against its predecessors does; by default nothing): called at each
        arming, after which the device's values start afresh.

        Parameters
        ----------
        jumps : int
            Frames to come that may each jump from the one before (an arming whose bytes
            are answered twice: a write before the set-up, at the old value, and one
            after it, at the new).
        """

    def feed(self, data: bytes) -> list:
        """Bytes in, the values of the frames taken out.

        Parameters
        ----------
        data : bytes
            Bytes read from the link; a frame's incomplete tail is held for the next call.

        Returns
        -------
        list
            The values of the frames taken (:meth:`parse`'s, and :data:`MARK` for a
            one-byte answer), in their order; a new list.
        """
        out = []
        self.feed_into(data, out)
        return out

    def feed_into(self, data: bytes, out: list) -> int:
        """:meth:`feed` into a list the caller reuses (a real-time loop's: no list per
        call): the frames taken go to ``out[0]``, ``out[1]``, ... (appended beyond its
        length).

        Parameters
        ----------
        data : bytes
        out : list

        Returns
        -------
        int
            Frames taken.
        """
        buf = self._buf
        buf += data
        st = self.stats
        n = self.length
        cap = len(out)
        i = 0
        confirm = self.confirm_next
        marks = self.marks
        while len(buf) >= n or (marks and buf):
            if marks and not self._realigning and self.mark_at(buf):
                del buf[:1]                 # a one-byte answer asked for (class notes)
                if i < cap:
                    out[i] = MARK
                else:
                    out.append(MARK)
                i += 1
                st["marks"] = st.get("marks", 0) + 1
                continue
            if len(buf) < n:
                break
            v = self.parse(buf)
            if v is not None and confirm:
                # a frame only where the stream goes on in its framing (class notes)
                if len(buf) > n:
                    if not self.starts_frame(buf[n]):
                        st["unconfirmed"] += 1
                        v = None
                elif self._realigning:
                    break                   # found realigning: wait for the next byte
            if v is None:
                del buf[:1]
                st["skipped"] += 1
                self._realigning = True
                self.on_skip()
                continue
            self._realigning = False
            del buf[:n]
            if self.accept(v):
                if i < cap:
                    out[i] = v
                else:
                    out.append(v)
                i += 1
                st["frames"] += 1
        return i


class MappedDecoder:
    """A frame decoder whose outputs are mapped to the axis position [m] or [rad].

    Parameters
    ----------
    frames : object
        A decoder with ``feed(bytes) -> list`` and a ``stats`` dict.
    position : callable
        Frame -> position.
    """

    def __init__(self, frames, position) -> None:
        self.frames = frames
        self.stats = frames.stats
        self._position = position

    def feed(self, data: bytes) -> list:
        """Bytes in, the positions of the complete frames out.

        Parameters
        ----------
        data : bytes
            Bytes read from the link.

        Returns
        -------
        list
            ``position(frame)`` of each frame the frame decoder's ``feed`` gave [m] or
            [rad], in their order.
        """
        pos = self._position
        return [pos(fr) for fr in self.frames.feed(data)]

    def reset_prediction(self, jumps: int = 1, anchor=None) -> None:
        """Forget the frame decoder's prediction at an arming: its
        :meth:`AlignedDecoder.reset_prediction` (if it has one; else nothing).

        Parameters
        ----------
        jumps : int
            As :meth:`AlignedDecoder.reset_prediction`.
        anchor : optional
            The set-up's value in the frame decoder's units, passed on when given
            (:meth:`Driver.rearm_anchor`; the Haply decoder's ``anchor``).
        """
        reset = getattr(self.frames, "reset_prediction", None)
        if reset is not None:
            reset(jumps) if anchor is None else reset(jumps, anchor=anchor)
