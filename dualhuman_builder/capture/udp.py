"""The UDP side shared by ``mvn+udp://`` and ``vive+udp://``: bind, filter senders, read in batches.

URL: ``SCHEME://HOST:PORT[?allow=IP,IP&rcvbuf=BYTES]``. ``HOST`` is the address to bind, exactly as
the rig names it (``0.0.0.0`` for every interface; empty means ``127.0.0.1``: an ad-hoc capture
listens on loopback only unless told otherwise); ``PORT`` defaults to the device family's port.
``allow`` limits the senders: a datagram from any other address is dropped and counted in
``rejected_senders`` (the first from each new address is also reported as an event), so a stray
or hostile sender on the studio network cannot inject samples unnoticed. ``rcvbuf`` asks for a
kernel receive buffer (default 8 MiB; ``SO_RCVBUFFORCE`` when permitted, else capped by
``net.core.rmem_max``) so that bursts survive while the recorder writes.

Counters: ``datagrams``, ``bytes``, ``rejected_senders``, ``oversize`` (a datagram that filled
the 64 KiB read buffer, possibly cut), and ``kernel_drops`` — what the kernel dropped because the
receive buffer was full, read from ``/proc/net/udp`` (Linux), so loss before the decoder is seen.
"""

from __future__ import annotations

import ipaddress
import os
import select
import socket
from dataclasses import dataclass

from dualhuman_builder.capture.sources import RawPacket, Source, SourceError, now_ns, parse_source_url

READ_BUFFER = 65535
DEFAULT_RCVBUF = 8 << 20
#: Most datagrams one :meth:`UdpSource.read` returns, so a flood cannot starve the caller.
MAX_BATCH = 4096


@dataclass(frozen=True)
class UdpAddress:
    host: str
    port: int
    allow: frozenset[str] | None
    rcvbuf: int


def parse_udp_url(url: str, default_port: int, params: tuple[str, ...]) -> tuple[UdpAddress, dict[str, str]]:
    """The bind address, sender allow-list and buffer size of a UDP source URL, and its query."""
    parts, query = parse_source_url(url, params)
    try:
        port = parts.port
    except ValueError:
        raise SourceError(f"bad port in {url!r}", fix="write HOST:PORT with PORT 1-65535") from None
    host = parts.hostname or "127.0.0.1"
    if parts.path not in ("", "/"):
        raise SourceError(f"{url!r}: a UDP source takes no path", fix=f"write {parts.scheme}://HOST:PORT")
    allow = None
    if query.get("allow"):
        allow = set()
        for a in query["allow"].split(","):
            try:
                allow.add(str(ipaddress.ip_address(a.strip())))
            except ValueError:
                raise SourceError(f"allow={a!r} in {url!r} is not an IP address",
                                  fix="list sender IP addresses separated by commas") from None  # fmt: skip
        allow = frozenset(allow)
    try:
        rcvbuf = int(query.get("rcvbuf", DEFAULT_RCVBUF))
    except ValueError:
        raise SourceError(f"rcvbuf={query['rcvbuf']!r} is not a number of bytes") from None
    return UdpAddress(host, default_port if port is None else port, allow, rcvbuf), query


def _kernel_drops(sock: socket.socket) -> int | None:
    """Datagrams the kernel dropped for this socket (the ``drops`` column of /proc/net/udp[6])."""
    try:
        inode = str(os.fstat(sock.fileno()).st_ino)
    except OSError:
        return None
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(table) as f:
                next(f)
                for line in f:
                    cols = line.split()
                    if len(cols) >= 13 and cols[9] == inode:
                        return int(cols[12])
        except (OSError, StopIteration, ValueError):
            continue
    return None


class UdpSource(Source):
    """Base of the UDP sources: binds in ``__init__``; :meth:`read` returns datagrams as
    :class:`RawPacket`. Subclasses set ``kind``, ``PARAMS`` (including ``allow`` and ``rcvbuf``),
    ``DEFAULT_PORT`` and :meth:`make_decoder`."""

    DEFAULT_PORT = 0

    def __init__(self, url: str):
        super().__init__(url)
        self.address, self.query = parse_udp_url(url, self.DEFAULT_PORT, self.PARAMS)
        family = socket.AF_INET6 if ":" in self.address.host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            for opt in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
                if opt is None:
                    continue
                try:
                    self.sock.setsockopt(socket.SOL_SOCKET, opt, self.address.rcvbuf)
                    break
                except OSError:
                    continue
            self.sock.bind((self.address.host, self.address.port))
        except OSError as e:
            self.sock.close()
            raise SourceError(f"cannot listen on UDP {self.address.host}:{self.address.port} for {url!r} ({e.strerror})",
                              fix="another program (or a second recorder) may hold the port; choose another "
                                  "port, or bind an address this machine has") from None  # fmt: skip
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self._seen_rejected: set[str] = set()
        self._drops0 = _kernel_drops(self.sock) or 0
        self.decoder = self.make_decoder(url)

    def read(self, timeout: float) -> list[RawPacket]:
        if self.closed:
            return []
        out: list[RawPacket] = []
        try:
            ready, _, _ = select.select([self.sock], [], [], max(0.0, timeout))
        except (OSError, ValueError):
            return out
        if not ready:
            return out
        allow = self.address.allow
        recv = self.sock.recvfrom
        counters = self.counters
        while len(out) < MAX_BATCH:
            try:
                data, sender = recv(READ_BUFFER)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            t = now_ns()
            if allow is not None and sender[0] not in allow:
                counters["rejected_senders"] += 1
                if sender[0] not in self._seen_rejected:
                    self._seen_rejected.add(sender[0])
                    if self.decoder is not None:
                        self.decoder.event(t, "rejected-sender", self.kind,
                                           f"datagrams from {sender[0]}:{sender[1]} are not in allow= and are dropped")
                continue
            if len(data) >= READ_BUFFER:
                counters["oversize"] += 1
            counters["datagrams"] += 1
            out.append(RawPacket(t, data))
        return out

    def stats(self) -> dict[str, int]:
        drops = _kernel_drops(self.sock) if not self.closed else None
        if drops is not None:
            self.counters["kernel_drops"] = drops - self._drops0
        return super().stats()

    def close(self) -> None:
        if not self.closed:
            self.stats()
            self.sock.close()
        super().close()
