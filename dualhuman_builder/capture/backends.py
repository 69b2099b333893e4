"""Which capture transports can open on this machine: UDP, serial, CAN and USB, each tried for real.

Every probe returns a :class:`BackendProbe` and never raises. ``ok=False`` means the transport
cannot be used as things stand and ``fix`` says what to do; an absent *device* (no serial adapter,
no SocketCAN interface, no VIVE dongle) is not a fault of the machine and is reported as ``ok``
with a detail saying so. The round trips use real loopback paths: a UDP socket on 127.0.0.1,
pyserial's ``loop://`` and a pseudo-terminal, and python-can's ``virtual`` bus.
"""

from __future__ import annotations

import errno
import functools
import os
import socket
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

#: Default UDP port of the Xsens MVN real-time network stream.
MVN_PORT = 9763
#: UDP port of the triad_openvr VIVE bridge (and of our own bridge).
VIVE_BRIDGE_PORT = 8051
#: USB vendor id of Valve, and the product ids of the devices we read.
VALVE_VENDOR_ID = 0x28DE
VALVE_PRODUCTS = {0x2022: "VIVE Tracker", 0x2300: "VIVE Tracker v2", 0x2101: "Watchman dongle"}
#: ARPHRD_CAN: the link type of a SocketCAN interface in /sys/class/net/*/type.
ARPHRD_CAN = 280

_PAYLOAD = bytes(range(256))  # every byte value, so a text-mode or CR/LF-translating path shows up
UDEV_RULE = 'SUBSYSTEM=="usb", ATTRS{idVendor}=="28de", MODE="0666"'


@dataclass
class BackendProbe:
    """Outcome of one probe: ``name``, ``ok``, a human ``detail``, and a ``fix`` when not ok."""

    name: str
    ok: bool
    detail: str
    fix: str | None = None


def _error(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}"


# ----------------------------------------------------------------------------------------- UDP
def probe_udp_loopback() -> BackendProbe:
    """Bind an ephemeral UDP port on 127.0.0.1 and receive a datagram sent to it."""
    name = "udp loopback"
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx, socket.socket(
            socket.AF_INET, socket.SOCK_DGRAM
        ) as tx:
            rx.bind(("127.0.0.1", 0))
            rx.settimeout(2.0)
            port = rx.getsockname()[1]
            message = b"MXTP02" + _PAYLOAD[:200]
            tx.sendto(message, ("127.0.0.1", port))
            data, _ = rx.recvfrom(65535)
    except OSError as e:
        return BackendProbe(name, False, f"UDP round trip on 127.0.0.1 failed ({_error(e)})",
                            "check that the loopback interface is up (`ip link set lo up`)")
    if data != message:
        return BackendProbe(name, False, f"datagram came back altered ({len(data)} of {len(message)} bytes)")
    return BackendProbe(name, True, f"datagram of {len(message)} bytes round-tripped via 127.0.0.1:{port}")


def probe_udp_port(port: int, what: str) -> BackendProbe:
    """Whether UDP ``port`` can be bound on all interfaces (what a live receiver needs)."""
    name = f"udp :{port} ({what})"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                return BackendProbe(
                    name, False, f"port {port} is already bound by another process",
                    f"stop the other receiver (`ss -ulpn 'sport = :{port}'` shows it) or put another "
                    "port in the source URL",
                )
            if e.errno == errno.EACCES:
                return BackendProbe(name, False, f"not allowed to bind port {port} ({_error(e)})",
                                    "run as a user allowed to bind this port, or use a port above 1024")
            return BackendProbe(name, False, f"cannot bind port {port} ({_error(e)})")
    return BackendProbe(name, True, f"port {port} is free to bind")


# ----------------------------------------------------------------------------------------- serial
def probe_serial_ports() -> BackendProbe:
    """List serial ports (pyserial) and whether this user may open them."""
    name = "serial ports"
    try:
        from serial.tools import list_ports
    except ImportError as e:
        return BackendProbe(name, False, f"pyserial is not importable ({_error(e)})", "scripts/setup.sh")
    ports = sorted(list_ports.comports(), key=lambda p: p.device)
    if not ports:
        return BackendProbe(name, True, "no serial ports present (an MTi on USB appears as /dev/ttyUSB*)")
    denied = [p.device for p in ports if not os.access(p.device, os.R_OK | os.W_OK)]
    listed = ", ".join(p.device if p.description in (None, "n/a") else f"{p.device} ({p.description})"
                       for p in ports)
    if denied:
        return BackendProbe(
            name, False, f"{len(ports)} port(s): {listed}; no read/write permission on {', '.join(denied)}",
            "add yourself to the port's group (`sudo usermod -aG dialout $USER`, then log in again)",
        )
    return BackendProbe(name, True, f"{len(ports)} port(s): {listed}")


def _serial_round_trip(port, write) -> bytes:
    write(_PAYLOAD)
    got = b""
    deadline = time.monotonic() + 2.0
    while len(got) < len(_PAYLOAD) and time.monotonic() < deadline:
        got += port.read(len(_PAYLOAD) - len(got))
    return got


def probe_serial_loop() -> BackendProbe:
    """Round-trip all 256 byte values through ``serial.serial_for_url("loop://")``."""
    name = "serial loop://"
    try:
        import serial

        with serial.serial_for_url("loop://", timeout=0.5) as port:
            got = _serial_round_trip(port, port.write)
    except Exception as e:  # pyserial raises SerialException and OSError subclasses
        return BackendProbe(name, False, f"loop:// failed ({_error(e)})", "scripts/setup.sh (pyserial)")
    if got != _PAYLOAD:
        return BackendProbe(name, False, f"loop:// returned {len(got)} of {len(_PAYLOAD)} bytes intact")
    return BackendProbe(name, True, f"{len(_PAYLOAD)} bytes round-tripped")


def probe_serial_pty() -> BackendProbe:
    """Round-trip bytes both ways between a pty master and ``serial.Serial`` on its slave."""
    name = "serial pty"
    try:
        import serial
    except ImportError as e:
        return BackendProbe(name, False, f"pyserial is not importable ({_error(e)})", "scripts/setup.sh")
    try:
        master, slave = os.openpty()
    except OSError as e:
        return BackendProbe(name, False, f"cannot open a pseudo-terminal ({_error(e)})",
                            "mount devpts (/dev/pts) in this container or VM")
    try:
        path = os.ttyname(slave)
        with serial.Serial(path, baudrate=921600, timeout=0.5) as port:  # configures the tty raw
            to_port = _serial_round_trip(port, lambda b: os.write(master, b))
            port.write(_PAYLOAD)
            port.flush()
            to_master = b""
            deadline = time.monotonic() + 2.0
            while len(to_master) < len(_PAYLOAD) and time.monotonic() < deadline:
                to_master += os.read(master, len(_PAYLOAD) - len(to_master))
    except Exception as e:
        return BackendProbe(name, False, f"pty round trip failed ({_error(e)})")
    finally:
        os.close(slave)
        os.close(master)
    if to_port != _PAYLOAD or to_master != _PAYLOAD:
        return BackendProbe(name, False, f"pty altered the bytes ({len(to_port)} in, {len(to_master)} out of "
                                         f"{len(_PAYLOAD)}; tty not in raw mode?)")
    return BackendProbe(name, True, f"{len(_PAYLOAD)} bytes each way through {path}")


# ----------------------------------------------------------------------------------------- CAN
def probe_can_interfaces() -> BackendProbe:
    """The python-can interface names this installation knows."""
    name = "can interfaces"
    try:
        import can
    except ImportError as e:
        return BackendProbe(name, False, f"python-can is not importable ({_error(e)})", "scripts/setup.sh")
    names = sorted(can.interfaces.VALID_INTERFACES)
    return BackendProbe(name, True, f"python-can {can.__version__}: {', '.join(names)}")


def probe_can_virtual() -> BackendProbe:
    """Send one MTi quaternion frame (id 0x21) between two python-can ``virtual`` buses."""
    name = "can virtual"
    try:
        import can

        channel = f"dualhuman-doctor-{uuid.uuid4().hex[:8]}"
        sent = can.Message(arbitration_id=0x21, data=bytes([0x7F, 0xFF, 0, 0, 0, 0, 0, 0]), is_extended_id=False)
        with can.Bus(interface="virtual", channel=channel) as a, can.Bus(interface="virtual", channel=channel) as b:
            a.send(sent)
            got = b.recv(timeout=2.0)
    except Exception as e:  # python-can raises CanError and ImportError subclasses
        return BackendProbe(name, False, f"virtual bus failed ({_error(e)})", "scripts/setup.sh (python-can)")
    if got is None:
        return BackendProbe(name, False, "frame sent on the virtual bus never arrived")
    if got.arbitration_id != sent.arbitration_id or bytes(got.data) != bytes(sent.data):
        return BackendProbe(name, False, f"frame arrived altered: {got}")
    return BackendProbe(name, True, "one frame (id 0x21, 8 bytes) round-tripped")


def socketcan_interfaces() -> list[str]:
    """Names of the network interfaces of link type CAN (``/sys/class/net/*/type`` == 280)."""
    found = []
    for type_file in sorted(Path("/sys/class/net").glob("*/type")):
        try:
            if int(type_file.read_text().strip()) == ARPHRD_CAN:
                found.append(type_file.parent.name)
        except (OSError, ValueError):
            continue
    return found


def probe_socketcan() -> BackendProbe:
    """SocketCAN interfaces present (none is fine: only an MTi on a CAN adapter needs one)."""
    name = "socketcan"
    if not Path("/sys/class/net").is_dir():
        return BackendProbe(name, True, "no /sys/class/net on this system (SocketCAN is Linux-only)")
    found = socketcan_interfaces()
    if not found:
        return BackendProbe(name, True, "no CAN interfaces present (fine unless an MTi is on a CAN adapter; "
                                        "a test one: `ip link add dev vcan0 type vcan && ip link set up vcan0`)")
    states = []
    for iface in found:
        try:
            state = (Path("/sys/class/net") / iface / "operstate").read_text().strip()
        except OSError:
            state = "unknown"
        states.append(f"{iface} ({state})")
    down = [i for i, s in zip(found, states) if "(down)" in s]
    if down:
        return BackendProbe(name, False, f"CAN interfaces: {', '.join(states)}",
                            f"bring it up: `ip link set {down[0]} up type can bitrate 1000000`")
    return BackendProbe(name, True, f"CAN interfaces: {', '.join(states)}")


# ----------------------------------------------------------------------------------------- USB
def _libusb_backend():
    import usb.backend.libusb1

    return usb.backend.libusb1.get_backend()


def probe_usb_backend() -> BackendProbe:
    """Whether pyusb finds a libusb-1.0 library to talk to USB devices (VIVE HID)."""
    name = "usb backend"
    try:
        backend = _libusb_backend()
    except ImportError as e:
        return BackendProbe(name, False, f"pyusb is not importable ({_error(e)})", "scripts/setup.sh")
    if backend is None:
        return BackendProbe(name, False, "pyusb finds no libusb-1.0 library",
                            "apt-get install libusb-1.0-0")
    lib = getattr(getattr(backend, "lib", None), "_name", None) or "libusb-1.0"
    return BackendProbe(name, True, f"pyusb uses {lib}")


def _valve_devices_sysfs() -> list[tuple[int, int, int, Path]]:
    """``(product id, bus, address, device node)`` of Valve devices listed under /sys/bus/usb."""
    found = []
    for dev in sorted(Path("/sys/bus/usb/devices").glob("*")):
        try:
            if int((dev / "idVendor").read_text(), 16) != VALVE_VENDOR_ID:
                continue
            pid = int((dev / "idProduct").read_text(), 16)
            bus = int((dev / "busnum").read_text())
            address = int((dev / "devnum").read_text())
        except (OSError, ValueError):
            continue
        found.append((pid, bus, address, Path(f"/dev/bus/usb/{bus:03d}/{address:03d}")))
    return found


def probe_vive_usb() -> BackendProbe:
    """Valve USB devices present (trackers, Watchman dongles) and whether this user may open them.

    Uses pyusb when libusb is there (opening each device to read its serial), else /sys/bus/usb.
    No device present is reported as ok.
    """
    name = "vive usb"
    devices: list[tuple[int, str, str | None]] = []  # (product id, where, problem)
    try:
        backend = _libusb_backend()
    except ImportError:
        backend = None
    if backend is not None:
        import usb.core
        import usb.util

        try:
            found = list(usb.core.find(find_all=True, idVendor=VALVE_VENDOR_ID, backend=backend))
        except usb.core.USBError as e:
            return BackendProbe(name, False, f"cannot enumerate USB devices ({_error(e)})",
                                "check that /dev/bus/usb is visible (containers: pass it through)")
        for dev in found:
            where = f"bus {dev.bus:03d} device {dev.address:03d}"
            problem = None
            try:
                serial_number = usb.util.get_string(dev, dev.iSerialNumber) if dev.iSerialNumber else None
                if serial_number:
                    where += f", serial {serial_number}"
            except usb.core.USBError as e:
                problem = "permission denied" if e.errno == errno.EACCES else _error(e)
            except (ValueError, NotImplementedError):
                pass  # opened fine but has no readable serial string
            devices.append((dev.idProduct, where, problem))
        how = "pyusb"
    else:
        for pid, bus, address, node in _valve_devices_sysfs():
            ok = os.access(node, os.R_OK | os.W_OK)
            devices.append((pid, f"bus {bus:03d} device {address:03d}", None if ok else "permission denied"))
        how = "sysfs (no libusb)"
    if not devices:
        return BackendProbe(name, True, f"no Valve USB devices present (vendor 0x28de, looked via {how})")
    listed = "; ".join(
        f"{VALVE_PRODUCTS.get(pid, f'product 0x{pid:04x}')} at {where}" + (f" [{problem}]" if problem else "")
        for pid, where, problem in devices
    )
    if any(problem == "permission denied" for _, _, problem in devices):
        return BackendProbe(
            name, False, f"{listed}",
            f"allow access with a udev rule: echo '{UDEV_RULE}' | sudo tee /etc/udev/rules.d/60-vive.rules "
            "&& sudo udevadm control --reload-rules && sudo udevadm trigger, then replug",
        )
    if any(problem for _, _, problem in devices):
        return BackendProbe(name, False, listed, "replug the device; check `dmesg` for USB errors")
    return BackendProbe(name, True, listed)


# ----------------------------------------------------------------------------------------- all
#: ``(name, probe)`` of every probe, in the order they run (UDP, serial, CAN, USB).
CAPTURE_PROBES: tuple[tuple[str, Callable[[], BackendProbe]], ...] = (
    ("udp loopback", probe_udp_loopback),
    (f"udp :{MVN_PORT} (mvn)", functools.partial(probe_udp_port, MVN_PORT, "mvn")),
    (f"udp :{VIVE_BRIDGE_PORT} (vive bridge)", functools.partial(probe_udp_port, VIVE_BRIDGE_PORT, "vive bridge")),
    ("serial ports", probe_serial_ports),
    ("serial loop://", probe_serial_loop),
    ("serial pty", probe_serial_pty),
    ("can interfaces", probe_can_interfaces),
    ("can virtual", probe_can_virtual),
    ("socketcan", probe_socketcan),
    ("usb backend", probe_usb_backend),
    ("vive usb", probe_vive_usb),
)


def probe_capture_backends() -> list[BackendProbe]:
    """Run every probe of :data:`CAPTURE_PROBES`; a probe that raises is reported as not ok."""
    results = []
    for name, probe in CAPTURE_PROBES:
        try:
            results.append(probe())
        except Exception as e:  # a probe bug must not hide the other probes' answers
            results.append(BackendProbe(name, False, f"probe raised {_error(e)}"))
    return results
