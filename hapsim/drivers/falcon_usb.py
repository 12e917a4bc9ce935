"""The Novint Falcon's USB link on the host: pyftdi (a user-space FTDI driver) over pyusb.

The Falcon is an FTDI FT232R behind USB id ``0403:cb48`` (libnifalcon,
``include/falcon/core/FalconComm.h`` and ``doc/DoxygenMainpage.h``). libnifalcon talks to
it in user space, as libusb control and bulk transfers (``src/comm/FalconCommLibUSB.cpp``):
purges, latency timer, baud divisors, DTR/RTS, bulk reads whose every 64-byte USB packet
starts with the FTDI's two status bytes. This module does the same through **pyftdi**
(``pip install 'hapsim[falcon]'``), which issues those control transfers itself
(``Ftdi.set_baudrate``, ``set_latency_timer``, ``set_dtr``, ``purge_buffers``) and strips
the status bytes in ``read_data``.

Why pyftdi and not the kernel's ``ftdi_sio`` (``new_id`` with ``0403 cb48``, a
``/dev/ttyUSB*`` driven with pyserial): the loader's handshake needs a DTR pulse and three
exact baud divisors (0x4138 = 9600 baud, 0x15 = 142,857, 0x2 = 1.5 Mbaud); through
``ftdi_sio`` they are termios calls whose USB transfers the kernel computes, and the only
test bench here would be a pty, which has no modem lines and no baud rate: the loader's
path could not be tested at all. With pyftdi the transfers are made in this process, so
the tests put an emulated FT232R under pyusb (:mod:`hapsim.emulated.ftdi_usb`, a pyusb
backend) and the real pyftdi code runs above it: every control transfer the Falcon would
receive is decoded and checked by the emulated chip (the divisors against libnifalcon's
constants, DTR's edge resetting the loader), and the bulk data carries the status bytes.
pyftdi's own virtual backend (``pyftdi/tests/backend``) was the first candidate: it is not
in pyftdi's wheel (0.57.2), and it ignores ``SET_MODEM_CTRL`` (no DTR), which the loader
needs. What the tests cannot reach: libusb and the kernel's usbfs (a real bus, its
timing and errors), the FT232R's own timing (latency timer, FIFO sizes), and Novint's
firmware (docs/devices.md, "The Novint Falcon over USB").

Device selection (``--port``): ``ftdi://0x0403:0xcb48/1`` (the first Falcon),
``ftdi://0x0403:0xcb48:N/1`` (the N-th, from 0, in the order libusb lists them) or
``ftdi://0x0403:0xcb48:SERIAL/1`` (by the FT232R's serial number).
"""

from __future__ import annotations

import errno as _errno
import re
import time

from hapsim.errors import ConfigError, DeviceError, FirmwareEchoError

__all__ = ["FALCON_VID", "FALCON_PID", "DEFAULT_URL", "UDEV_RULE", "FT232R_CLOCK_HZ",
           "ft232r_baud", "BAUD_OF_DIVISOR", "parse_url", "FalconUSB", "load_firmware_link",
           "explain_usb_error", "usbfs_sink", "OUT_ENDPOINT"]

#: The FT232R's bulk OUT endpoint (host -> UART).
OUT_ENDPOINT = 0x02

#: The Falcon's USB vendor and product ids (libnifalcon ``FalconComm.h``).
FALCON_VID, FALCON_PID = 0x0403, 0xCB48
#: ``--port`` for the first Falcon.
DEFAULT_URL = "ftdi://0x0403:0xcb48/1"
#: The udev rule that lets a user in group ``plugdev`` open the Falcon (libnifalcon ships
#: one like it: ``linux/40-novint-falcon-udev.rules``).
UDEV_RULE = ('SUBSYSTEM=="usb", ATTR{idVendor}=="0403", ATTR{idProduct}=="cb48", '
             'MODE="0660", GROUP="plugdev"')
#: The FT232R's baud-rate generator clock [Hz] (FTDI AN232B-05).
FT232R_CLOCK_HZ = 3_000_000
#: The sub-integer divisor codes of the FT232R (bits 14-16 of the divisor), in eighths
#: (FTDI AN232B-05: 0, 1/2, 1/4, 1/8, 3/8, 5/8, 3/4, 7/8).
_FRAC_EIGHTHS = (0, 4, 2, 1, 3, 5, 6, 7)
#: The baud rates pyftdi is asked for so that it sends libnifalcon's divisors: 0x15 (the
#: loading rate, 3 MHz / 21) and 0x2 (normal mode, 3 MHz / 2); 9600 gives 0x4138.
BAUD_OF_DIVISOR = {0x15: 142_857, 0x2: 1_500_000}

_URL = re.compile(r"^ftdi://0x0*403:0x0*cb48(?::([^/]+))?/1$", re.IGNORECASE)


def ft232r_baud(divisor: int) -> float:
    """The baud rate an FT232R runs at for a divisor (``wValue | wIndex << 16`` of its
    ``SET_BAUD_RATE`` request).

    Parameters
    ----------
    divisor : int
        Bits 0-13 the integer part, bits 14-16 the sub-integer code.

    Returns
    -------
    float
        [baud]: ``3 MHz / (n + f)``, with the special divisors 0 (3 Mbaud) and 1 (2 Mbaud)
        (FTDI application note AN232B-05, "Configuring FT232R, FT2232 and FT232B baud
        rates").
    """
    d = int(divisor)
    n, code = d & 0x3FFF, (d >> 14) & 0x7
    if n == 0 and code == 0:
        return 3_000_000.0
    if n == 1 and code == 0:
        return 2_000_000.0
    return FT232R_CLOCK_HZ / (n + _FRAC_EIGHTHS[code] / 8.0)


def parse_url(url: str | None):
    """The Falcon a ``--port`` names.

    Parameters
    ----------
    url : str or None
        None: the first Falcon; else one of the module's forms.

    Returns
    -------
    (int or None, str or None)
        ``(index, serial)``: the N-th Falcon, or the one with that serial number
        (``(0, None)`` for the first).

    Raises
    ------
    ConfigError
        Any other text (key ``--port``, the valid forms listed).
    """
    if url is None:
        return 0, None
    m = _URL.match(url.strip())
    if not m:
        raise ConfigError(f"{url!r} is not a Falcon's USB address; valid: {DEFAULT_URL} "
                          "(the first), ftdi://0x0403:0xcb48:N/1 (the N-th from 0), "
                          "ftdi://0x0403:0xcb48:SERIAL/1", key="--port")
    sel = m.group(1)
    if sel is None:
        return 0, None
    return (int(sel), None) if sel.isdigit() else (None, sel)


def _usb_errno(exc):
    """The errno of a pyusb error, looked for through pyftdi's wrapping (it raises
    ``FtdiError`` from the ``USBError``, the latter kept as the context)."""
    seen = 0
    while exc is not None and seen < 5:
        if getattr(exc, "errno", None) is not None:
            return exc.errno
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def explain_usb_error(exc, doing: str) -> DeviceError:
    """A :class:`DeviceError` that says what happened and what to check.

    Parameters
    ----------
    exc : Exception
        A pyusb ``USBError`` or pyftdi ``FtdiError`` (its cause searched for the errno).
    doing : str
        What the host was doing (``"opening the Falcon"``, ``"packet 812"``).

    Returns
    -------
    DeviceError
    """
    e = _usb_errno(exc)
    if e == _errno.EACCES:
        return DeviceError(
            f"{doing}: permission denied on the Falcon's USB device. Install the udev rule "
            f"(as root, in /etc/udev/rules.d/40-novint-falcon.rules):\n  {UDEV_RULE}\n"
            "then 'udevadm control --reload && udevadm trigger', add yourself to group "
            "plugdev, unplug and plug the Falcon (docs/devices.md)")
    if e == _errno.ENODEV:
        return DeviceError(f"{doing}: the Falcon went away (USB unplugged or its power "
                           f"lost): {exc}")
    if e == _errno.EBUSY:
        return DeviceError(f"{doing}: the Falcon's interface is held by another program "
                           f"(libnifalcon, a second hapsim) or a kernel driver: {exc}")
    if e in (_errno.ETIMEDOUT, getattr(_errno, "ETIME", -1)):
        return DeviceError(f"{doing}: the USB transfer timed out (a hub or cable fault?): "
                           f"{exc}")
    return DeviceError(f"{doing}: USB error: {exc}")


def usbfs_sink(bus: int, address: int, fd_dir: str = "/proc/self/fd") -> tuple:
    """The host watchdog's sink on a real Falcon: libusb's own file of the device, found
    among this process's open files (Linux: ``/dev/bus/usb/BBB/DDD``).

    The Falcon's firmware holds its last command (no watchdog published) and pyftdi's
    libusb owns the device in the host's process, so a watchdog in its own process writes
    through that file, inherited: usbfs keeps the interface's claim per open file, so the
    kernel takes the watchdog's transfer as the host's
    (:func:`hapsim.drivers.torque_watchdog._usbfs_writer`).

    Parameters
    ----------
    bus, address : int
        The device's USB bus and address (pyusb's ``Device.bus``, ``Device.address``).
    fd_dir : str
        Where the process's open files are listed.

    Returns
    -------
    (str, int, int)
        ``("usbfs", fd, OUT_ENDPOINT)``.

    Raises
    ------
    OSError
        No such file open (not Linux, or libusb reaches the device another way), with
        the path looked for.
    """
    import os
    want = f"/dev/bus/usb/{int(bus):03d}/{int(address):03d}"
    try:
        names = os.listdir(fd_dir)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot list {fd_dir} to find {want}: {exc.strerror}") \
            from None
    for name in sorted(names, key=lambda n: int(n) if n.isdigit() else -1):
        try:
            if os.readlink(os.path.join(fd_dir, name)) == want:
                return "usbfs", int(name), OUT_ENDPOINT
        except (OSError, ValueError):
            continue
    raise OSError(_errno.ENOENT, f"libusb's file {want} is not open in this process")


class FalconUSB:
    """The Falcon's FT232R opened with pyftdi (module notes).

    Parameters
    ----------
    url : str, optional
        Which Falcon (:func:`parse_url`); None: the first.
    backend : object, optional
        A pyusb backend (:class:`hapsim.emulated.ftdi_usb.VirtualUSB` in the tests); None:
        libusb-1.0 (``usb.backend.libusb1``).
    read_timeout : float
        How long :meth:`exchange` waits for an answer [s].

    Attributes
    ----------
    ftdi : pyftdi.ftdi.Ftdi
    written, read_bytes : int
        Bytes moved.
    sink : callable or None
        Gives the host watchdog's sink (the emulated chip's
        :meth:`~hapsim.emulated.ftdi_usb.VirtualFT232R.side_channel`); None: libusb's file
        (:meth:`watchdog_sink`).

    Raises
    ------
    DeviceError
        pyftdi or pyusb not installed, no libusb, no Falcon found (the FTDI devices seen
        listed), permission denied (the udev rule), the device busy.
    ConfigError
        A bad ``url``.
    """

    def __init__(self, url: str | None = None, *, backend=None,
                 read_timeout: float = 0.05) -> None:
        from hapsim.option_values import option_value
        read_timeout = option_value("read_timeout", read_timeout, "s", low=0, low_ok=False)
        index, serial = parse_url(url)
        try:
            import usb.core
            import usb.util
            from pyftdi.ftdi import Ftdi
        except ImportError as exc:
            raise DeviceError("the Falcon's USB link needs pyftdi: pip install "
                              f"'hapsim[falcon]' ({exc})") from None
        if backend is None:
            import usb.backend.libusb1
            backend = usb.backend.libusb1.get_backend()
            if backend is None:
                raise DeviceError("no libusb-1.0 for pyusb: install it (Debian/Ubuntu: "
                                  "apt install libusb-1.0-0; macOS: brew install libusb)")
        self._usb_util = usb.util
        self.read_timeout = float(read_timeout)
        self.written = self.read_bytes = 0
        self.ftdi = None
        #: Where a host watchdog writes (:meth:`watchdog_sink`); None: libusb's file.
        self.sink = None
        try:
            found = list(usb.core.find(find_all=True, idVendor=FALCON_VID,
                                       idProduct=FALCON_PID, backend=backend))
        except usb.core.USBError as exc:
            raise explain_usb_error(exc, "listing USB devices") from None
        dev = self._select(found, index, serial, usb, backend)
        self.device = dev
        ftdi = Ftdi()
        try:
            ftdi.open_from_device(dev, 1)
            # pyusb claims the interface at the first bulk transfer; claim it now, so
            # that a program holding it is said at the open
            usb.util.claim_interface(dev, 0)
        except Exception as exc:  # pyftdi raises FtdiError, pyusb USBError
            try:
                usb.util.dispose_resources(dev)
            except Exception:
                pass
            raise explain_usb_error(exc, "opening the Falcon") from None
        self.ftdi = ftdi

    @staticmethod
    def _select(found, index, serial, usb, backend):
        if not found:
            others = []
            try:
                others = [f"{d.idVendor:04x}:{d.idProduct:04x}" for d in
                          usb.core.find(find_all=True, idVendor=FALCON_VID, backend=backend)]
            except Exception:
                pass
            raise DeviceError(
                "no Novint Falcon (USB 0403:cb48) found: is it plugged in and is 'lsusb -d "
                "0403:cb48' listing it? (the Falcon needs its power supply too)"
                + (f"; FTDI devices seen: {', '.join(others)}" if others else ""))
        if serial is not None:
            for d in found:
                try:
                    s = usb.util.get_string(d, d.iSerialNumber) if d.iSerialNumber else None
                except Exception as exc:
                    raise explain_usb_error(exc, "reading a Falcon's serial number") from None
                if s == serial:
                    return d
            raise DeviceError(f"no Falcon with serial number {serial!r} among the "
                              f"{len(found)} found")
        if index >= len(found):
            raise DeviceError(f"Falcon {index} asked for, {len(found)} found (counting "
                              "from 0)")
        return found[index]

    # ------------------------------------------------------------------ line settings
    def line(self, **settings) -> None:
        """Apply :class:`hapsim.drivers.falcon.FalconFirmwareLoader` line settings as
        pyftdi calls (each one USB control transfer, or two for ``purge``).

        Parameters
        ----------
        **settings
            ``purge`` (bool), ``latency_ms`` [ms], ``baud`` [baud], ``baud_divisor``
            (0x15 or 0x2: :data:`BAUD_OF_DIVISOR`), ``bits`` (``"8N1"``), ``flow`` (None),
            ``rts``, ``dtr`` (0 or 1).

        Raises
        ------
        DeviceError
            A transfer failed (:func:`explain_usb_error`).
        ConfigError
            An unknown setting or divisor (a programming error).
        """
        f = self.ftdi
        try:
            for key, value in settings.items():
                if key == "purge":
                    if value:
                        f.purge_buffers()
                elif key == "latency_ms":
                    f.set_latency_timer(int(value))
                elif key == "baud":
                    f.set_baudrate(int(value))
                elif key == "baud_divisor":
                    if value not in BAUD_OF_DIVISOR:
                        raise ConfigError(f"baud divisor {value:#x} not one of "
                                          f"{[hex(k) for k in BAUD_OF_DIVISOR]}",
                                          key="baud_divisor")
                    f.set_baudrate(BAUD_OF_DIVISOR[value])
                elif key == "bits":
                    if value != "8N1":
                        raise ConfigError(f"line {value!r}: only 8N1", key="bits")
                    f.set_line_property(8, 1, "N")
                elif key == "flow":
                    f.set_flowctrl("" if value is None else value)
                elif key == "rts":
                    f.set_rts(bool(value))
                elif key == "dtr":
                    f.set_dtr(bool(value))
                else:
                    raise ConfigError(f"unknown line setting {key!r}", key=key)
        except ConfigError:
            raise
        except Exception as exc:
            raise explain_usb_error(exc, f"setting {sorted(settings)}") from None

    # ------------------------------------------------------------------ bytes
    def write(self, data: bytes) -> None:
        """Write bytes (one or more bulk OUT transfers).

        Parameters
        ----------
        data : bytes
            What to write (counted in :attr:`written`).

        Raises
        ------
        DeviceError
            The transfer failed (the device gone, ...).
        """
        try:
            self.ftdi.write_data(data)
        except Exception as exc:
            raise explain_usb_error(exc, "writing to the Falcon") from None
        self.written += len(data)

    def read(self, n: int, timeout: float | None = None, done=None) -> bytes:
        """Read up to ``n`` bytes, waiting at most ``timeout`` [s] (pyftdi strips the
        FTDI's two status bytes of each USB packet).

        Parameters
        ----------
        n : int
            Most bytes.
        timeout : float, optional
            [s]; default :attr:`read_timeout`.
        done : callable, optional
            ``done(bytes) -> bool``: stop early once true.

        Returns
        -------
        bytes
            What came (fewer than ``n`` when the time ran out).

        Raises
        ------
        DeviceError
            The transfer failed.
        """
        end = time.monotonic() + (self.read_timeout if timeout is None else timeout)
        out = bytearray()
        try:
            while len(out) < n:
                # the deadline is looked at before the read, so the last read comes after
                # it: a host descheduled past the deadline reads what came meanwhile
                # (a late reply is a late sample, not a missing one)
                late = time.monotonic() >= end
                out += self.ftdi.read_data(n - len(out))
                if (done is not None and done(bytes(out))) or len(out) >= n:
                    break
                if late:
                    break
        except Exception as exc:
            raise explain_usb_error(exc, "reading from the Falcon") from None
        self.read_bytes += len(out)
        return bytes(out)

    def watchdog_sink(self) -> tuple:
        """Where a host watchdog in its own process writes the zero command: the
        emulated chip's side channel when one was given (:attr:`sink`), else libusb's
        file of the device (:func:`usbfs_sink`).

        Returns
        -------
        tuple
            A :class:`hapsim.drivers.torque_watchdog.TorqueWatchdog` ``sink``.

        Raises
        ------
        OSError
            None found (the reason).
        """
        if self.sink is not None:
            return self.sink()
        return usbfs_sink(self.device.bus, self.device.address)

    def exchange(self, send: bytes, n: int, done=None, timeout: float | None = None) -> bytes:
        """Write ``send``, then read up to ``n`` bytes (:meth:`read`).

        Parameters
        ----------
        send : bytes
            What to write.
        n : int
            Most bytes read.
        done : callable, optional
            ``done(bytes) -> bool``: stop reading early once true.
        timeout : float, optional
            Longest wait for the reply [s]; default :attr:`read_timeout`.

        Returns
        -------
        bytes
            What came (fewer than ``n`` when the time ran out).

        Raises
        ------
        DeviceError
            The write or the read failed.
        """
        self.write(send)
        return self.read(n, timeout, done)

    def close(self) -> None:
        """Close the interface (errors of a device already gone are ignored)."""
        f, self.ftdi = self.ftdi, None
        if f is None:
            return
        try:
            f.close()
        except Exception:
            pass
        try:
            self._usb_util.dispose_resources(self.device)
        except Exception:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def load_firmware_link(link, image: bytes, check_tries: int = 100,
                       timeout: float = 0.1) -> dict:
    """The host's side of the firmware-load handshake over a link with ``line(**)`` and
    ``exchange(send, n, done, timeout)`` (:class:`FalconUSB`, or the emulator wrapped so).

    Parameters
    ----------
    link : object
    image : bytes
        The firmware image (Novint's, from the user: hapsim does not ship it).
    check_tries : int
        Attempts of the first check (libnifalcon: 100).
    timeout : float
        Wait for each answer [s].

    Returns
    -------
    dict
        ``checks`` (attempts of the first check), ``chunks`` (image chunks echoed),
        ``bytes`` (image bytes echoed).

    Raises
    ------
    DeviceError
        An empty image; the loader's first check unanswered (what came, what to check).
    FirmwareEchoError
        ``'A'`` not echoed; an image chunk's echo short or differing (the image byte's
        offset, the byte sent and the byte echoed).
    """
    from hapsim.drivers.falcon import FIRMWARE_CHUNK, FalconFirmwareLoader
    image = bytes(image)
    if not image:
        raise DeviceError("the firmware image is empty")
    out = {"checks": 0, "chunks": 0, "bytes": 0}
    n_chunks = -(-len(image) // FIRMWARE_CHUNK)
    last = b""
    a_echoed = False
    for step in FalconFirmwareLoader(image, check_tries).steps():
        if step[0] == "line":
            link.line(**step[1])
        elif step[0] == "check":
            _, send, want, tries = step
            for _ in range(tries):
                out["checks"] += 1
                last = link.exchange(send, len(want) + 1,
                                     lambda b, w=want: b.endswith(w), timeout)
                if last.endswith(want):              # a leading 00 on some hosts
                    break
            else:
                raise DeviceError(
                    f"the Falcon's loader did not answer {send.hex(' ')} with "
                    f"{want.hex(' ')} in {tries} tries (last answer: "
                    f"{last.hex(' ') or 'nothing'}). Check: the Falcon's power supply is "
                    "plugged in; the firmware is not already running (unplug its USB and "
                    "power, plug them again, load again)")
        elif not a_echoed:                          # the loader's 'A', then the image
            _, send, want = step
            a_echoed = True
            got = link.exchange(send, 1, None, timeout)
            if got != want:
                raise FirmwareEchoError(
                    f"the Falcon's loader did not echo 'A' at the loading baud rate (got "
                    f"{got.hex(' ') or 'nothing'}): the loader answered at 9600 baud but "
                    "not at 142,857; unplug and plug the Falcon and load again")
        else:
            _, send, want = step
            got = link.exchange(send, len(want), None, timeout)
            off = out["bytes"]
            k = next((i for i in range(min(len(got), len(want))) if got[i] != want[i]),
                     None)
            if k is not None:
                raise FirmwareEchoError(
                    f"the Falcon's loader echoed image byte {off + k} (chunk "
                    f"{out['chunks'] + 1} of {n_chunks}) as {got[k]:#04x}, sent "
                    f"{want[k]:#04x}: the load failed. Unplug and plug the Falcon and load "
                    "again; if it fails at another byte, suspect the cable or hub, at the "
                    "same byte, the image file")
            if len(got) < len(want):
                raise FirmwareEchoError(
                    f"the Falcon's loader echoed {len(got)} of the {len(want)} bytes of "
                    f"chunk {out['chunks'] + 1} of {n_chunks} (image bytes {off}.."
                    f"{off + len(want) - 1}) within {timeout * 1e3:g} ms: it stopped "
                    f"answering at image byte {off + len(got)}. Unplug and plug the Falcon "
                    "and load again")
            out["chunks"] += 1
            out["bytes"] += len(got)
    return out
