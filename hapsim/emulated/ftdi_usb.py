"""An emulated FTDI FT232R on pyusb's backend interface, its UART wired to an emulated
device: the real pyftdi (and pyusb) code runs above it, as it would above libusb.

:class:`VirtualUSB` is a pyusb backend (``usb.backend.IBackend``: enumerate, descriptors,
open/claim, control and bulk transfers) holding :class:`VirtualFT232R` chips. A chip
decodes the FTDI vendor requests the host sends (``SIO_RESET`` with its purges,
``SET_MODEM_CTRL`` DTR/RTS, ``SET_FLOW_CTRL``, ``SET_BAUD_RATE`` divisor, ``SET_DATA``,
``SET_LATENCY_TIMER``, ``GET_LATENCY_TIMER``, ``POLL_MODEM_STATUS``, ``SET_BITMODE``;
libftdi's and libnifalcon's request numbers) into ``line(**settings)`` calls on its
device (:class:`hapsim.emulated.falcon_device.FalconDevice`: ``dtr``, ``rts``,
``baud_divisor``, ``latency_ms``, ``purge``, ``bits``, ``flow``), passes bulk OUT bytes
(endpoint 0x02) to ``device.feed`` and returns its answer on bulk IN (endpoint 0x81) in
64-byte USB packets, each starting with the FT232R's two status bytes (modem status
0x01 as the FT232R sets it, line status 0x60: transmitter empty), as
``FalconCommLibUSB.cpp`` reads them (``output + 2``). A request the chip does not know
stalls (``USBError`` EPIPE), as a real one does.

Faults: seeded byte loss and bit flips per direction, duplicated bytes to the host (:class:`hapsim.emulated.driver_mock.ByteFaults`
on the UART: what the FT232R and the Falcon's MCU exchange), an unplug after a number of
bulk transfers (every later transfer raises ``USBError`` ENODEV, libusb's
``LIBUSB_ERROR_NO_DEVICE``, and the device leaves the bus), a permission refusal on open
(EACCES, ``LIBUSB_ERROR_ACCESS``), a busy interface (EBUSY).

Time: a device on its own clock (``device.wall``, :class:`hapsim.emulated.falcon_device.
FalconDevice`'s default) says when its answer is ready (``device.ready_at`` on
``device.now()``'s clock: the Falcon's firmware answers a packet at its next tick); a bulk
IN returns only the bytes ready by then, as the chip has them from the UART only then.
A bulk IN with an answer on its way but not ready waits for it at most :data:`POLL_S`
(a real chip NAKs meanwhile). Not modelled: the latency timer's timing (a bulk IN returns
what the device has answered by then, the status bytes alone when nothing), the FIFOs' sizes, the
baud rate's time on the wire (a byte takes no time), USB timeouts.
"""

from __future__ import annotations

import errno
import time
from array import array
from types import SimpleNamespace

__all__ = ["VirtualFT232R", "VirtualUSB", "SIO", "POLL_S"]

#: Longest wait of a bulk IN for an answer the device has on its way [s]: a read
#: before the answer is ready waits this (or until it is ready), as a real chip NAKs the
#: IN token meanwhile, instead of returning the status bytes alone at once.
POLL_S = 2e-4

#: FTDI vendor requests (libftdi ``ftdi.h``; libnifalcon ``FalconCommLibUSB.cpp``).
SIO = {"reset": 0x00, "modem_ctrl": 0x01, "flow_ctrl": 0x02, "baud": 0x03, "data": 0x04,
       "poll_modem_status": 0x05, "latency": 0x09, "get_latency": 0x0A, "bitmode": 0x0B}
_PACKET = 64            # full-speed bulk packet: 2 status bytes + 62 data bytes
_OUT_EP, _IN_EP = 0x02, 0x81


def _usb_error(text: str, code: int):
    import usb.core
    return usb.core.USBError(text, None, code)


class VirtualFT232R:
    """One emulated FT232R with a device on its UART (module notes).

    Parameters
    ----------
    device : object
        ``line(**settings)`` and ``feed(bytes) -> bytes`` (the device's answer).
    vid, pid : int
        USB ids (the Falcon's: 0x0403, 0xCB48).
    serial : str
        The serial-number string.
    faults : hapsim.emulated.driver_mock.ByteFaults, optional
        Byte faults on the UART (``rx``: host -> device, ``tx``: device -> host).
    unplug_after : int, optional
        Bulk transfers after which the chip leaves the bus.
    deny_access, busy : bool
        Refuse the open (EACCES) or the interface claim (EBUSY).
    dup_tx : float
        Probability that a device -> host byte comes twice (counted in ``duplicated``).
    seed : int
        Seed of the duplication.

    Attributes
    ----------
    requests : list of (int, int, int)
        Every vendor request received: ``(bRequest, wValue, wIndex)``.
    latency_ms, divisor, dtr, rts : int
        The chip's state from the requests.
    transfers : int
        Bulk transfers served.
    faults_on : bool
        The faults and duplication apply (True at first).
    plugged : bool
    """

    def __init__(self, device, *, vid: int = 0x0403, pid: int = 0xCB48,
                 serial: str = "HAPSIM0001", faults=None, unplug_after: int | None = None,
                 deny_access: bool = False, busy: bool = False, dup_tx: float = 0.0,
                 seed: int = 0, bus: int = 1, address: int = 7) -> None:
        import numpy as np
        self.device = device
        self.faults = faults
        self.dup_tx = float(dup_tx)
        self._rng = np.random.default_rng(int(seed))
        self.duplicated = 0
        self.faults_on = True
        self.unplug_after = unplug_after
        self.deny_access = deny_access
        self.busy = busy
        self.requests: list = []
        self.latency_ms = 16
        self.divisor = None
        self.dtr = self.rts = 0
        self.transfers = 0
        self.plugged = True
        self._to_host = bytearray()
        self._later: list = []               # (device time ready [s], bytes) not yet in
        self._side = None                    # the side channel's pipe (read, write)
        self._side_buf = bytearray()
        #: Bytes of one side-channel transfer (the Falcon's 16-byte packet).
        self.side_size = 16
        #: Side-channel transfers fed to the device (:meth:`_side_in`): what the device
        #: took of the watchdog's writes, counted on this side of the wire.
        self.side_taken = 0
        self.strings = {1: "FTDI", 2: "hapsim emulated FT232R", 3: serial}
        self.desc = SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0,
            bDeviceSubClass=0, bDeviceProtocol=0, bMaxPacketSize0=8, idVendor=vid,
            idProduct=pid, bcdDevice=0x0600,          # FT232R (pyftdi reads the chip from it)
            iManufacturer=1, iProduct=2, iSerialNumber=3, bNumConfigurations=1,
            address=address, bus=bus, port_number=1, port_numbers=(1,), speed=2)
        self.config = SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=32, bNumInterfaces=1,
            bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80, bMaxPower=45,
            extra_descriptors=b"")
        self.interface = SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
            bNumEndpoints=2, bInterfaceClass=0xFF, bInterfaceSubClass=0xFF,
            bInterfaceProtocol=0xFF, iInterface=2, extra_descriptors=b"")
        self.endpoints = [SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=ep, bmAttributes=2,
            wMaxPacketSize=_PACKET, bInterval=0, bRefresh=0, bSynchAddress=0,
            extra_descriptors=b"") for ep in (_IN_EP, _OUT_EP)]

    # ------------------------------------------------------------------ faults
    def unplug(self) -> None:
        """Leave the bus: every later transfer fails with ENODEV."""
        self.plugged = False

    def _alive(self) -> None:
        if not self.plugged:
            raise _usb_error("No such device (it may have been disconnected)", errno.ENODEV)

    def _count_transfer(self) -> None:
        self._alive()
        self.transfers += 1
        if self.unplug_after is not None and self.transfers > self.unplug_after:
            self.unplug()
            self._alive()

    # ------------------------------------------------------------------ control
    def control(self, bm: int, req: int, value: int, index: int, data) -> int:
        """One control transfer; IN data written into ``data``. Returns its length.

        Parameters
        ----------
        bm : int
            ``bmRequestType``: bits 5-6 the type (0 standard, 2 vendor), bit 7 IN.
        req, value, index : int
            ``bRequest`` (a standard GET_DESCRIPTOR or an :data:`SIO` request), ``wValue``,
            ``wIndex``.
        data : array of int (``array("B")``)
            OUT: the request's data; IN: the buffer its answer is written into.

        Returns
        -------
        int
            Bytes transferred: 1 (``GET_LATENCY_TIMER``), 2 (``POLL_MODEM_STATUS``), the
            string descriptor's bytes that fit, else ``len(data)``.

        Raises
        ------
        usb.core.USBError
            EPIPE (a stall): a class or reserved request, an unknown vendor request, a
            ``SIO_RESET`` value other than 0-2, a bit mode other than the UART's, a standard
            request other than GET_DESCRIPTOR of a known string; ENODEV: unplugged.
        """
        self._alive()
        if bm & 0x60 == 0x00:                        # standard: descriptors
            return self._standard(bm, req, value, index, data)
        if bm & 0x60 != 0x40:
            raise _usb_error("Pipe error", errno.EPIPE)
        self.requests.append((req, value, index))
        dev = self.device
        if req == SIO["reset"]:
            if value == 0:                            # reset: both buffers
                self._to_host.clear()
                self._later.clear()
                dev.line(purge=True)
            elif value == 1:                          # purge RX: what goes to the host
                self._to_host.clear()
                self._later.clear()
            elif value == 2:                          # purge TX: what goes to the device
                dev.line(purge=True)
            else:
                raise _usb_error("Pipe error", errno.EPIPE)
        elif req == SIO["modem_ctrl"]:
            mask, level = value >> 8, value & 0xFF
            if mask & 0x1:
                self.dtr = level & 0x1
                dev.line(dtr=self.dtr)
            if mask & 0x2:
                self.rts = (level >> 1) & 0x1
                dev.line(rts=self.rts)
        elif req == SIO["flow_ctrl"]:
            flow = index >> 8
            dev.line(flow=None if flow == 0 else
                     {1: "rtscts", 2: "dtrdsr", 4: "xonxoff"}.get(flow, flow))
        elif req == SIO["baud"]:
            # FT232R: wIndex bit 0 is the divisor's bit 16 (AN232B-05)
            self.divisor = value | ((index & 0x1) << 16)
            dev.line(baud_divisor=self.divisor)
        elif req == SIO["data"]:
            bits, parity, stop = value & 0xFF, (value >> 8) & 0x7, (value >> 11) & 0x3
            dev.line(bits=f"{bits}{'NOEMS'[parity] if parity < 5 else '?'}"
                          f"{({0: '1', 1: '1.5', 2: '2'}).get(stop, '?')}")
        elif req == SIO["latency"]:
            self.latency_ms = value & 0xFF
            dev.line(latency_ms=self.latency_ms)
        elif req == SIO["get_latency"]:
            data[0] = self.latency_ms
            return 1
        elif req == SIO["poll_modem_status"]:
            data[0], data[1] = self._status()
            return 2
        elif req == SIO["bitmode"]:
            if (value >> 8) & 0xFF != 0:              # only the UART (reset) mode
                raise _usb_error("Pipe error", errno.EPIPE)
        else:
            raise _usb_error("Pipe error", errno.EPIPE)
        return len(data)

    def _standard(self, bm, req, value, index, data) -> int:
        if req != 0x06 or not bm & 0x80:              # GET_DESCRIPTOR only
            raise _usb_error("Pipe error", errno.EPIPE)
        kind, i = value >> 8, value & 0xFF
        if kind != 3:
            raise _usb_error("Pipe error", errno.EPIPE)
        if i == 0:
            buf = bytes((4, 3, 0x09, 0x04))           # en-US
        elif i in self.strings:
            s = self.strings[i].encode("utf-16-le")
            buf = bytes((2 + len(s), 3)) + s
        else:
            raise _usb_error("Pipe error", errno.EPIPE)
        n = min(len(buf), len(data))
        data[:n] = array("B", buf[:n])
        return n

    @staticmethod
    def _status():
        return 0x01, 0x60

    # ------------------------------------------------------------------ side channel
    def side_channel(self) -> tuple:
        """A second writer of bulk OUT bytes, for another process: the host's watchdog
        (:mod:`hapsim.drivers.torque_watchdog`'s ``stamped`` sink), as a real chip takes
        a bulk transfer from any process holding libusb's file.

        Returns
        -------
        (str, int)
            ``("stamped", fd)``: the write end of a pipe; each write is the writer's
            ``time.monotonic_ns()`` (8 bytes, little endian) and then one
            :attr:`side_size`-byte transfer, taken at that time by the device's own clock
            (:meth:`_side_in`) whenever the chip next serves the host: the emulated device
            runs in the host's process, so a write made while the host did not run lands
            in the device's past, where a real chip would have taken it.

        Raises
        ------
        OSError
            A device in lockstep (its time is the host's transfers: a write from
            elsewhere has no time in it), or no pipe could be made.
        """
        if getattr(self.device, "wall", None) is None:
            raise OSError(errno.EPERM, "a lockstep device: its time is the host's transfers")
        if self._side is None:
            import os
            r, w = os.pipe()
            os.set_blocking(r, False)
            self._side = (r, w)
        return "stamped", self._side[1]

    def _side_in(self) -> None:
        """The side channel's transfers, each fed to the device at its own time."""
        if self._side is None:
            return
        import os
        rec = 8 + self.side_size
        try:
            self._side_buf += os.read(self._side[0], 65536)
        except BlockingIOError:
            pass
        while len(self._side_buf) >= rec:
            t_ns = int.from_bytes(self._side_buf[:8], "little")
            data = bytes(self._side_buf[8:rec])
            del self._side_buf[:rec]
            # (a device on its own clock: side_channel refuses a lockstep one)
            self._take_out(data, self.device.now() - (time.monotonic_ns() - t_ns) * 1e-9)
            self.side_taken += 1

    def close_side(self) -> None:
        """Close the side channel's pipe (idempotent)."""
        import os
        side, self._side = self._side, None
        self._side_buf.clear()
        if side is not None:
            for fd in side:
                os.close(fd)

    # ------------------------------------------------------------------ bulk
    def bulk_out(self, data) -> int:
        """Host -> device bytes: through the faults to ``device.feed``; its answer kept
        for the host (through the faults).

        Parameters
        ----------
        data : bytes-like
            The bulk OUT transfer's bytes.

        Returns
        -------
        int
            ``len(data)``: every byte taken (those the faults drop included).

        Raises
        ------
        usb.core.USBError
            ENODEV: the chip is unplugged, or leaves the bus at this transfer
            (``unplug_after``).
        """
        self._count_transfer()
        self._side_in()
        self._take_out(bytes(data))
        return len(data)

    def _take_out(self, b: bytes, now: float | None = None) -> None:
        """Bulk OUT bytes ``b`` through the faults to the device (at its time ``now``:
        default the device's own)."""
        on = self.faults_on
        if on and self.faults is not None:
            b = self.faults.rx(b)
        if not b:
            ans = b""
        elif now is None:
            ans = self.device.feed(b)
        else:
            ans = self.device.feed(b, now=now)
        if on and ans and self.faults is not None:
            ans = self.faults.tx(ans)
        if on and ans and self.dup_tx > 0:
            twice = self._rng.random(len(ans)) < self.dup_tx
            if twice.any():
                self.duplicated += int(twice.sum())
                ans = bytes(b for k, b in enumerate(ans) for _ in range(1 + int(twice[k])))
        if ans and getattr(self.device, "wall", None) is not None:
            self._later.append((self.device.ready_at, ans))
        else:
            self._to_host += ans

    def bulk_in(self, buff) -> int:
        """Device -> host: USB packets of the two status bytes and up to 62 data bytes,
        as many as ``buff`` holds (at least the status bytes).

        Parameters
        ----------
        buff : array of int (``array("B")``)
            The read's buffer, written in place; its length is the bytes asked for.

        Returns
        -------
        int
            Bytes written into ``buff``: 2 status bytes per packet and the data (0 when
            ``buff`` holds fewer than 2 bytes).

        Raises
        ------
        usb.core.USBError
            ENODEV: the chip is unplugged, or leaves the bus at this transfer.
        """
        self._count_transfer()
        self._side_in()
        if self._later:
            now = self.device.now()
            if not self._to_host and self._later[0][0] > now:
                # nothing for the host yet and an answer on its way: the chip NAKs the IN
                # token until it has bytes (its latency timer aside), so a real bulk read
                # blocks; here it waits a poll's time (0.2 ms, finer than full-speed USB's
                # 1 ms frames) instead of returning at once, which made pyftdi's read
                # loop spin a core (a loop at SCHED_FIFO spinning starves the machine)
                time.sleep(min(self._later[0][0] - now, POLL_S))
                now = self.device.now()
            while self._later and self._later[0][0] <= now:
                self._to_host += self._later.pop(0)[1]
        s0, s1 = self._status()
        pos = 0
        size = len(buff)
        while pos + 2 <= size:
            take = min(_PACKET - 2, size - pos - 2, len(self._to_host))
            buff[pos], buff[pos + 1] = s0, s1
            if take:
                buff[pos + 2:pos + 2 + take] = array("B", self._to_host[:take])
                del self._to_host[:take]
            pos += 2 + take
            if not self._to_host or take < _PACKET - 2:
                break
        return pos


class VirtualUSB:
    """A pyusb backend (``usb.backend.IBackend``'s methods) over :class:`VirtualFT232R`
    chips: ``usb.core.find(..., backend=VirtualUSB([chip]))`` finds them, pyftdi opens
    them (module notes).

    Parameters
    ----------
    chips : list of VirtualFT232R
    """

    def __init__(self, chips) -> None:
        self.chips = list(chips)
        self._handles = 0

    # enumeration and descriptors
    def enumerate_devices(self):
        """The chips on the bus (an unplugged one is not).

        Returns
        -------
        list of VirtualFT232R
            The plugged chips, in order: pyusb's ``dev`` for the methods below.
        """
        return [c for c in self.chips if c.plugged]

    def get_device_descriptor(self, dev):
        """The device descriptor (``bcdDevice`` 0x0600: an FT232R).

        Parameters
        ----------
        dev : VirtualFT232R
            A chip of :meth:`enumerate_devices`.

        Returns
        -------
        types.SimpleNamespace
            The chip's ``desc``: the USB fields (``idVendor``, ``idProduct``, ...) and its
            ``bus``, ``address``, ``port_number``, ``speed``.
        """
        return dev.desc

    def get_configuration_descriptor(self, dev, config):
        """The one configuration.

        Parameters
        ----------
        dev : VirtualFT232R
        config : int
            The configuration's index (not checked: there is one).

        Returns
        -------
        types.SimpleNamespace
            The chip's ``config`` descriptor (``bConfigurationValue`` 1, one interface).
        """
        return dev.config

    def get_interface_descriptor(self, dev, intf, alt, config):
        """The one interface (vendor class, two bulk endpoints).

        Parameters
        ----------
        dev : VirtualFT232R
        intf, alt, config : int
            Interface, alternate setting and configuration indices (not checked).

        Returns
        -------
        types.SimpleNamespace
            The chip's ``interface`` descriptor.
        """
        return dev.interface

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        """Bulk IN 0x81 and bulk OUT 0x02, 64 bytes.

        Parameters
        ----------
        dev : VirtualFT232R
        ep : int
            The endpoint's index in the interface: 0 (bulk IN 0x81) or 1 (bulk OUT 0x02).
        intf, alt, config : int
            Interface, alternate setting and configuration indices (not checked).

        Returns
        -------
        types.SimpleNamespace
            The endpoint descriptor (``wMaxPacketSize`` 64).

        Raises
        ------
        IndexError
            ``ep`` other than 0 or 1.
        """
        return dev.endpoints[ep]

    # handles
    def open_device(self, dev):
        """A handle (EACCES when the chip denies access: no udev rule).

        Parameters
        ----------
        dev : VirtualFT232R

        Returns
        -------
        types.SimpleNamespace
            ``dev`` (the chip) and ``handle`` (the handles opened so far, from 1).

        Raises
        ------
        usb.core.USBError
            ENODEV: the chip is unplugged; EACCES: it denies access (``deny_access``).
        """
        if not dev.plugged:
            raise _usb_error("No such device (it may have been disconnected)", errno.ENODEV)
        if dev.deny_access:
            raise _usb_error("Access denied (insufficient permissions)", errno.EACCES)
        self._handles += 1
        return SimpleNamespace(dev=dev, handle=self._handles)

    def close_device(self, dev_handle) -> None:
        """The chip's side channel closed (a watchdog's writes end with the host's
        handle, as libusb's file).

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        """
        dev_handle.dev.close_side()

    def set_configuration(self, dev_handle, config_value) -> None:
        """Only configuration 1 exists.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        config_value : int
            ``bConfigurationValue`` asked (not checked).

        Raises
        ------
        usb.core.USBError
            ENODEV: the chip is unplugged.
        """
        dev_handle.dev._alive()

    def get_configuration(self, dev_handle) -> int:
        """Configuration 1.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.

        Returns
        -------
        int
            1.
        """
        return 1

    def set_interface_altsetting(self, dev_handle, intf, altsetting) -> None:
        """Only alternate setting 0 exists.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        intf, altsetting : int
            Interface and alternate setting (ignored).
        """

    def claim_interface(self, dev_handle, intf) -> None:
        """Claim (EBUSY when the chip says another program holds it).

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        intf : int
            The interface (not checked).

        Raises
        ------
        usb.core.USBError
            ENODEV: the chip is unplugged; EBUSY: it is busy (``busy``).
        """
        dev_handle.dev._alive()
        if dev_handle.dev.busy:
            raise _usb_error("Resource busy", errno.EBUSY)

    def release_interface(self, dev_handle, intf) -> None:
        """Release (never fails, as after an unplug).

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        intf : int
            The interface (ignored).
        """

    def is_kernel_driver_active(self, dev_handle, intf) -> bool:
        """No kernel driver.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        intf : int
            The interface (ignored).

        Returns
        -------
        bool
            False.
        """
        return False

    def detach_kernel_driver(self, dev_handle, intf) -> None:
        """Nothing attached.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        intf : int
            The interface (ignored).
        """

    def attach_kernel_driver(self, dev_handle, intf) -> None:
        """Nothing to attach.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        intf : int
            The interface (ignored).
        """

    def reset_device(self, dev_handle) -> None:
        """A USB reset (the chip's state kept).

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.

        Raises
        ------
        usb.core.USBError
            ENODEV: the chip is unplugged.
        """
        dev_handle.dev._alive()

    def clear_halt(self, dev_handle, ep) -> None:
        """No halted endpoint.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        ep : int
            The endpoint's address (ignored).
        """

    # transfers
    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data,
                      timeout):
        """A control transfer (:meth:`VirtualFT232R.control`).

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        bmRequestType, bRequest, wValue, wIndex : int
            The setup packet's fields.
        data : array of int (``array("B")``)
            OUT: the data; IN: the buffer the answer is written into.
        timeout : int
            pyusb's timeout [ms] (ignored: no transfer waits).

        Returns
        -------
        int
            Bytes transferred (:meth:`VirtualFT232R.control`).

        Raises
        ------
        usb.core.USBError
            As :meth:`VirtualFT232R.control` (EPIPE, ENODEV).
        """
        return dev_handle.dev.control(bmRequestType, bRequest, wValue, wIndex, data)

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        """Bulk OUT to endpoint 0x02.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        ep : int
            The endpoint's address: 0x02.
        intf : int
            The interface (ignored).
        data : bytes-like
            The bytes to the device.
        timeout : int
            pyusb's timeout [ms] (ignored).

        Returns
        -------
        int
            Bytes taken (:meth:`VirtualFT232R.bulk_out`).

        Raises
        ------
        usb.core.USBError
            EPIPE: another endpoint; ENODEV: the chip is unplugged or leaves the bus.
        """
        if ep != _OUT_EP:
            raise _usb_error("Pipe error", errno.EPIPE)
        return dev_handle.dev.bulk_out(data)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        """Bulk IN from endpoint 0x81.

        Parameters
        ----------
        dev_handle : types.SimpleNamespace
            A handle of :meth:`open_device`.
        ep : int
            The endpoint's address: 0x81.
        intf : int
            The interface (ignored).
        buff : array of int (``array("B")``)
            The read's buffer, written in place.
        timeout : int
            pyusb's timeout [ms] (ignored: the wait is at most :data:`POLL_S`).

        Returns
        -------
        int
            Bytes written into ``buff`` (:meth:`VirtualFT232R.bulk_in`).

        Raises
        ------
        usb.core.USBError
            EPIPE: another endpoint; ENODEV: the chip is unplugged or leaves the bus.
        """
        if ep != _IN_EP:
            raise _usb_error("Pipe error", errno.EPIPE)
        return dev_handle.dev.bulk_in(buff)

    def _no_such_endpoint(self, *args, **kw):
        """Interrupt and isochronous transfers: the FT232R has no such endpoint."""
        raise _usb_error("Pipe error", errno.EPIPE)

    intr_write = intr_read = iso_write = iso_read = _no_such_endpoint
