"""``vive+usb://[?serial=LHR-1A2B3C4D&timeout=S]``: a VIVE tracker's IMU over USB HID, read with
pyusb (libusb-1.0). Only the IMU: the pose needs the lighthouse solver and is not in the HID
stream (:mod:`dualhuman_builder.capture.wire.vive_hid`); use ``vive+udp://`` for poses.

Parameters: ``serial`` the tracker's USB serial number (default: the first Valve tracker or
Watchman dongle found); ``timeout`` seconds to wait for the device to appear when opening
(default 0: fail at once; enumerated every 0.25 s).

A tracker on a cable sends the 0x20 IMU report decoded here. Through a Watchman dongle
(0x2101) the IMU arrives inside the dongle's wireless reports, which this source does not unpack
(they are counted as ``unknown_id``, with one ``unknown-report`` event per report id).

Opening fails with a :class:`~dualhuman_builder.capture.sources.SourceError` that says what to do
when pyusb finds no libusb backend, no Valve device is plugged in, or this user may not open it
(a udev rule); a device unplugged while reading raises
:class:`~dualhuman_builder.capture.sources.SourceLost`.
"""

from __future__ import annotations

import errno
import time
from collections import deque

import numpy as np

from dualhuman_builder.capture.backends import UDEV_RULE
from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.capture.sources import (Decoder, RawPacket, Source, SourceError, SourceLost, now_ns,
                                               number_param, parse_source_url)  # fmt: skip
from dualhuman_builder.capture.wire.vive_hid import (ACC_SCALE, GYRO_SCALE, PRODUCTS, TICK_HZ, VALVE_VENDOR_ID,
                                                     ViveHidError, decode_imu_report, ticks_to_ns)  # fmt: skip

DEFAULT_DEVICE = "vive-usb"
#: Slots remembered to recognise a sample repeated by a later report (each report repeats two).
SEEN_WINDOW = 8
#: Most reports one :meth:`ViveUsbSource.read` returns.
MAX_BATCH = 256
#: A device-time gap (s) between consecutive new samples that is reported as a ``gap`` event.
GAP_EVENT_S = 1.0

_LOOKED_FOR = ", ".join(f"0x{pid:04x} {name}" for pid, name in PRODUCTS.items())
_READONLY_NAN4 = np.full(4, np.nan)
_READONLY_NAN3 = np.full(3, np.nan)
_READONLY_NAN4.setflags(write=False)
_READONLY_NAN3.setflags(write=False)


class ViveUsbDecoder(Decoder):
    """IMU reports -> one :class:`ImuSample` per new IMU sample, in sample order.

    Each sample: ``device`` (the URL's ``serial``, else ``"vive-usb"``); ``counter`` the u8
    ``seq``; ``device_time_ns`` the 48 MHz tick count **unwrapped** across the u32 wrap (every
    89.48 s) and converted to ns (floor), monotonic; ``host_time_ns`` the report's arrival;
    ``acceleration (3,)`` m/s^2 and ``rate_of_turn (3,)`` rad/s in the **sensor** frame, raw
    (no device calibration applied); ``orientation (4,)`` and ``magnetic_field (3,)`` NaN: the
    tracker measures neither; ``status`` 0.

    A slot whose ``(seq, time_ticks)`` was among the last 8 seen is a repeat and is dropped;
    any other slot is new, its time ``(ticks - last ticks) mod 2^32`` ticks after the last one's
    (right for gaps shorter than one wrap, 89 s). Lost samples come from the ``seq`` gap; once
    the sample period is known (from consecutive samples), a gap longer than 256 periods adds
    the whole multiples of 256 that the u8 ``seq`` cannot show.

    Counters: ``packets``, ``bytes``, ``samples``; ``duplicate`` (repeated slots, about two per
    report in a steady stream), ``lost`` (samples never received); bad reports, dropped:
    ``unknown_id`` (not the 0x20 IMU report), ``truncated`` (< 52 bytes), ``bad_length``
    (> 52 bytes). Events: ``unknown-report`` (once per report id), ``gap`` (more than 1 s of
    device time between consecutive samples).
    """

    def __init__(self, device: str = DEFAULT_DEVICE):
        super().__init__()
        self.device = device
        self._last_seq: int | None = None
        self._last_ticks = 0
        self._total_ticks = 0
        self._period: float | None = None
        self._seen: deque[tuple[int, int]] = deque(maxlen=SEEN_WINDOW)
        self._unknown_ids: set[int] = set()

    def feed(self, packet: RawPacket) -> list:
        c = self.counters
        c["packets"] += 1
        c["bytes"] += len(packet.data)
        try:
            slots = decode_imu_report(packet.data)
        except ViveHidError as e:
            c[e.counter] += 1
            if e.counter == "unknown_id" and packet.data[0] not in self._unknown_ids:
                self._unknown_ids.add(packet.data[0])
                self.event(packet.host_time_ns, "unknown-report", self.device,
                           f"HID report 0x{packet.data[0]:02x} is not the IMU report and is not decoded")  # fmt: skip
            return []
        ref = slots[0].seq
        out = []
        for s in sorted(slots, key=lambda s: ((s.seq - ref + 128) % 256) - 128):  # the ring, oldest first
            key = (s.seq, s.time_ticks)
            if key in self._seen:
                c["duplicate"] += 1
                continue
            self._seen.append(key)
            if self._last_seq is None:
                self._total_ticks = s.time_ticks
            else:
                dt = (s.time_ticks - self._last_ticks) % 2**32
                dseq = (s.seq - self._last_seq) % 256 or 256
                missing = dseq - 1
                if self._period is not None and self._period > 0:
                    missing += 256 * max(0, round((dt / self._period - dseq) / 256))
                if dseq == 1 and dt > 0:
                    self._period = dt if self._period is None else 0.9 * self._period + 0.1 * dt
                c["lost"] += missing
                if dt > GAP_EVENT_S * TICK_HZ:
                    self.event(packet.host_time_ns, "gap", self.device,
                               f"{dt / TICK_HZ:.3f} s of device time without IMU samples ({missing} lost)")
                self._total_ticks += dt
            self._last_seq, self._last_ticks = s.seq, s.time_ticks
            acc = np.array(s.acc, dtype=np.float64) * ACC_SCALE
            gyro = np.array(s.gyro, dtype=np.float64) * GYRO_SCALE
            acc.setflags(write=False)
            gyro.setflags(write=False)
            out.append(ImuSample(device=self.device, counter=s.seq, device_time_ns=ticks_to_ns(self._total_ticks),
                                 host_time_ns=int(packet.host_time_ns), orientation=_READONLY_NAN4, acceleration=acc,
                                 rate_of_turn=gyro, magnetic_field=_READONLY_NAN3))  # fmt: skip
        c["samples"] += len(out)
        return out


def _options(url: str, params: tuple[str, ...]) -> tuple[str | None, float]:
    parts, query = parse_source_url(url, params)
    if parts.netloc or parts.path not in ("", "/"):
        raise SourceError(f"{url!r}: vive+usb takes no host or path", fix="write vive+usb://?serial=LHR-1A2B3C4D")
    serial = query.get("serial") or None
    timeout = number_param(query, "timeout", float, 0.0)
    if not timeout >= 0:
        raise SourceError(f"timeout={query['timeout']!r} in {url!r} must be seconds >= 0")
    return serial, timeout


def _permission_error(what: str) -> SourceError:
    return SourceError(
        f"permission denied opening {what}",
        fix=f"allow access with a udev rule: echo '{UDEV_RULE}' | sudo tee /etc/udev/rules.d/60-vive.rules "
        "&& sudo udevadm control --reload-rules && sudo udevadm trigger, then replug the device",
    )


class ViveUsbSource(Source):
    """Opens a Valve tracker (or Watchman dongle) with pyusb, claims its HID interface
    (detaching the kernel's hid driver if bound) and reads HID reports from its interrupt IN
    endpoint. ``find_library``: passed to pyusb's libusb1 ``get_backend`` (a function from a
    library name to its path) for unusual installs. See the module docstring for the URL and
    errors, :class:`ViveUsbDecoder` for samples and counters. Transport counter: ``usb_errors``
    (transfers that failed without the device going away)."""

    kind = "vive-usb"
    PARAMS = ("serial", "timeout")

    def __init__(self, url: str, *, find_library=None):
        super().__init__(url)
        self.serial, wait_s = _options(url, self.PARAMS)
        try:
            import usb.backend.libusb1
            import usb.core
            import usb.util
        except ImportError as e:
            raise SourceError(f"pyusb is not importable ({e})", fix="scripts/setup.sh (pip install pyusb)") from None
        self._usb = usb
        backend = usb.backend.libusb1.get_backend(find_library=find_library)
        if backend is None:
            raise SourceError(f"cannot open {url!r}: pyusb finds no libusb-1.0 backend",
                              fix="apt-get install libusb-1.0-0")  # fmt: skip
        deadline = time.monotonic() + wait_s
        while True:
            dev, seen = self._find(backend)
            if dev is not None or time.monotonic() >= deadline:
                break
            time.sleep(min(0.25, max(0.0, deadline - time.monotonic())))
        if dev is None:
            waited = f" within {wait_s:g} s" if wait_s else ""
            if self.serial and seen:
                raise SourceError(f"no Valve device with serial {self.serial!r}{waited}; found {', '.join(seen)}",
                                  fix="check the serial= in the URL (or leave it out to take the first)")  # fmt: skip
            raise SourceError(
                f"no Valve USB device{' with serial ' + repr(self.serial) if self.serial else ''} found{waited} "
                f"(looked for vendor 0x{VALVE_VENDOR_ID:04x}, products {_LOOKED_FOR})",
                fix="plug the tracker in by USB cable (or its Watchman dongle); in a container pass /dev/bus/usb "
                    "through; add timeout=S to wait for it",
            )  # fmt: skip
        self.device = dev
        self.device_label = f"{PRODUCTS[dev.idProduct]} at bus {dev.bus:03d} device {dev.address:03d}"
        self._interface: int | None = None
        self._reattach = False
        try:
            self._open()
        except BaseException:
            self._release()
            raise
        self.decoder = self.make_decoder(url)

    def _serial_of(self, dev) -> str | None:
        usb = self._usb
        if not dev.iSerialNumber:
            return None
        try:
            return usb.util.get_string(dev, dev.iSerialNumber)
        except usb.core.USBError as e:
            if e.errno == errno.EACCES:
                raise _permission_error(f"Valve device {dev.idVendor:04x}:{dev.idProduct:04x} at bus {dev.bus:03d} "
                                        f"device {dev.address:03d}") from None  # fmt: skip
            return None
        except (ValueError, NotImplementedError):
            return None

    def _find(self, backend):
        """``(device or None, descriptions of the Valve devices seen)``."""
        usb = self._usb
        try:
            found = list(usb.core.find(find_all=True, idVendor=VALVE_VENDOR_ID, backend=backend,
                                       custom_match=lambda d: d.idProduct in PRODUCTS))  # fmt: skip
        except usb.core.USBError as e:
            if e.errno == errno.EACCES:
                raise _permission_error("the USB device list") from None
            raise SourceError(f"cannot enumerate USB devices ({e})",
                              fix="check that /dev/bus/usb is visible (containers: pass it through)") from None  # fmt: skip
        found.sort(key=lambda d: (d.bus or 0, d.address or 0))
        if not self.serial:
            return (found[0] if found else None), [PRODUCTS[d.idProduct] for d in found]
        seen = []
        for d in found:
            s = self._serial_of(d)
            if s == self.serial:
                return d, seen
            seen.append(f"{PRODUCTS[d.idProduct]} {s or '(no serial)'}")
        return None, seen

    def _open(self) -> None:
        usb, dev = self._usb, self.device
        try:
            try:
                cfg = dev.get_active_configuration()
            except usb.core.USBError as e:
                if e.errno in (errno.EACCES, errno.ENODEV):
                    raise
                dev.set_configuration()
                cfg = dev.get_active_configuration()
            for intf in cfg:
                if intf.bInterfaceClass != 3:  # HID
                    continue
                ep = usb.util.find_descriptor(intf, custom_match=lambda e: (
                    usb.util.endpoint_direction(e.bEndpointAddress) == usb.util.ENDPOINT_IN
                    and usb.util.endpoint_type(e.bmAttributes) == usb.util.ENDPOINT_TYPE_INTR))  # fmt: skip
                if ep is not None:
                    break
            else:
                raise SourceError(f"{self.device_label} has no HID interface with an interrupt IN endpoint",
                                  fix="this device is not a VIVE tracker or dongle that this source reads")  # fmt: skip
            number = intf.bInterfaceNumber
            try:
                if dev.is_kernel_driver_active(number):
                    dev.detach_kernel_driver(number)
                    self._reattach = True
            except NotImplementedError:
                pass
            usb.util.claim_interface(dev, number)
            self._interface = number
            self._ep_address, self._ep_size = ep.bEndpointAddress, max(64, ep.wMaxPacketSize)
        except usb.core.USBError as e:
            if e.errno == errno.EACCES:
                raise _permission_error(self.device_label) from None
            if e.errno == errno.EBUSY:
                raise SourceError(f"{self.device_label} is busy ({e})",
                                  fix="close SteamVR, libsurvive or another recorder that holds the tracker") from None  # fmt: skip
            if e.errno == errno.ENODEV:
                raise SourceError(f"{self.device_label} went away while it was opened", fix="replug it") from None
            raise SourceError(f"cannot open {self.device_label} ({e})", fix="replug it; check `dmesg`") from None

    def read(self, timeout: float) -> list[RawPacket]:
        if self.closed:
            return []
        usb = self._usb
        out: list[RawPacket] = []
        wait_ms = max(1, int(round(timeout * 1000)))  # pyusb reads 0 ms as "forever"
        while len(out) < MAX_BATCH:
            try:
                data = self.device.read(self._ep_address, self._ep_size, timeout=wait_ms if not out else 1)
            except usb.core.USBTimeoutError:
                break
            except usb.core.USBError as e:
                if e.errno == errno.ENODEV or getattr(e, "backend_error_code", None) == -4:  # LIBUSB_ERROR_NO_DEVICE
                    raise SourceLost(f"{self.device_label} was unplugged ({e})",
                                     fix="plug it back in and start a new take") from None  # fmt: skip
                if e.errno == errno.ETIMEDOUT:
                    break
                self.counters["usb_errors"] += 1
                break
            out.append(RawPacket(now_ns(), bytes(data)))
        return out

    @classmethod
    def make_decoder(cls, url: str) -> ViveUsbDecoder:
        serial, _ = _options(url, cls.PARAMS)
        return ViveUsbDecoder(serial or DEFAULT_DEVICE)

    def _release(self) -> None:
        usb, dev = self._usb, getattr(self, "device", None)
        if dev is None:
            return
        try:
            if self._interface is not None:
                usb.util.release_interface(dev, self._interface)
                if self._reattach:
                    dev.attach_kernel_driver(self._interface)
            usb.util.dispose_resources(dev)
        except (usb.core.USBError, NotImplementedError):
            pass  # the device is gone or never opened: nothing left to release
        self._interface = None

    def close(self) -> None:
        if not self.closed:
            self._release()
        super().close()
