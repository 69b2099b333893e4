"""The UDP side shared by ``mvn+udp://`` and ``vive+udp://``: bind, filter senders, read in batches.

URL: ``SCHEME://HOST:PORT[?allow=IP,IP&rcvbuf=BYTES]``. ``HOST`` is the address to bind, exactly as
the rig names it (``0.0.0.0`` for every interface; empty means ``127.0.0.1``: an ad-hoc capture
listens on loopback only unless told otherwise); ``PORT`` defaults to the device family's port.
``allow`` limits the senders: a datagram from any other address is dropped and counted in
``rejected_senders`` (the first from each new address is also reported as an event, up to
:data:`MAX_REJECTED_REPORTED` addresses), so a stray or hostile sender on the studio network cannot
inject samples unnoticed. ``rcvbuf`` asks for a kernel receive buffer (default 8 MiB) so that
bursts survive while the recorder writes: with ``SO_RCVBUFFORCE`` where the process may
(``CAP_NET_ADMIN``, e.g. root), else ``SO_RCVBUF``, which ``net.core.rmem_max`` caps. What the kernel
granted is :attr:`UdpSource.buffer_bytes` (Linux reports twice the size set: the doubled budget
it counts queued datagrams against, each costing its length plus about :data:`PACKET_OVERHEAD`);
less than asked is reported as an event ``small-rcvbuf`` that says how to raise the cap.

Transport events (``rejected-sender``, ``oversize``, ``small-rcvbuf``) are kept on the source,
not on its decoder (:meth:`UdpSource.pop_events`): the recorder reads them from the reader thread
and writes them to the take, whether decoding runs in its process or in another.

Counters: ``datagrams``, ``bytes``, ``rejected_senders``, ``oversize`` (a datagram that filled
the 64 KiB read buffer, possibly cut), and ``kernel_drops`` — what the kernel dropped because the
receive buffer was full, read from ``/proc/net/udp`` (Linux), so loss before the decoder is seen.
"""

from __future__ import annotations

import collections
import ipaddress
import os
import select
import socket
import sys
import time
from dataclasses import dataclass

from dualhuman_builder.capture.sources import RawPacket, Source, SourceError, SourceEvent, parse_source_url

READ_BUFFER = 65535
DEFAULT_RCVBUF = 8 << 20
#: Largest receive buffer a URL may ask for (the kernel takes an int; it doubles what it grants).
MAX_RCVBUF = 1 << 30
#: Most datagrams one :meth:`UdpSource.read` returns, so a flood cannot starve the caller.
MAX_BATCH = 4096
#: Linux's ``SO_RCVBUFFORCE`` (the socket module does not name it): a receive buffer above
#: ``net.core.rmem_max`` for a process with ``CAP_NET_ADMIN``.
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33 if sys.platform.startswith("linux") else None)
#: Bytes of receive buffer a queued datagram costs beyond its data (Linux loopback: 700-900).
PACKET_OVERHEAD = 1024
#: Distinct rejected sender addresses reported each by an event; more are counted only.
MAX_REJECTED_REPORTED = 32


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
    if not 1 <= rcvbuf <= MAX_RCVBUF:
        raise SourceError(f"rcvbuf={rcvbuf} in {url!r} is out of range", fix=f"give 1 to {MAX_RCVBUF} bytes")
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
    ``DEFAULT_PORT`` and :meth:`make_decoder`.

    ``buffer_bytes``: the receive buffer the kernel granted (what the recorder paces its reader
    by, with ``packet_overhead``); ``port``: the bound port."""

    DEFAULT_PORT = 0
    #: Bytes of receive buffer a queued datagram costs beyond its data (for the recorder's reader).
    packet_overhead = PACKET_OVERHEAD

    def __init__(self, url: str):
        super().__init__(url)
        self.address, self.query = parse_udp_url(url, self.DEFAULT_PORT, self.PARAMS)
        family = socket.AF_INET6 if ":" in self.address.host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        #: Transport events, appended by the reading thread and taken by :meth:`pop_events`.
        self.events: collections.deque[SourceEvent] = collections.deque()
        try:
            self.buffer_bytes = self._ask_rcvbuf(self.address.rcvbuf)
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
        if self.buffer_bytes < self.address.rcvbuf:
            self.event(time.monotonic_ns(), "small-rcvbuf", self.kind,
                       f"UDP {self.address.host}:{self.port}: asked for a {self.address.rcvbuf}-byte receive buffer, "
                       f"the kernel granted {self.buffer_bytes} (about {self.buffer_bytes // (128 + PACKET_OVERHEAD)} "
                       f"small datagrams); raise the cap with `sudo sysctl -w net.core.rmem_max="
                       f"{self.address.rcvbuf}`, or run the recorder with CAP_NET_ADMIN")  # fmt: skip

    def _ask_rcvbuf(self, size: int) -> int:
        """Set the receive buffer (forced where allowed); what the kernel granted, in bytes."""
        for opt in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
            if opt is None:
                continue
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, opt, size)
                break
            except OSError:  # EPERM without CAP_NET_ADMIN: fall back to the capped option
                continue
        return int(self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))

    def event(self, host_time_ns: int, kind: str, entity: str, message: str) -> None:
        """Report a transport event (taken by :meth:`pop_events`; thread-safe)."""
        self.events.append(SourceEvent(int(host_time_ns), kind, entity, message))

    def pop_events(self) -> list[SourceEvent]:
        """The transport events since the last call, in order (thread-safe)."""
        out = []
        pop = self.events.popleft
        while self.events:
            out.append(pop())
        return out

    def read(self, timeout: float) -> list[RawPacket]:
        """The datagrams waiting (at most :data:`MAX_BATCH`), waiting up to ``timeout`` s for the
        first; each stamped with ``time.monotonic_ns()`` as it is read. Counters are added once
        per call, not per datagram."""
        if self.closed:
            return []
        sock = self.sock
        try:
            ready, _, _ = select.select([sock], [], [], max(0.0, timeout))
        except (OSError, ValueError):
            return []
        if not ready:
            return []
        out: list[RawPacket] = []
        append = out.append
        clock = time.monotonic_ns
        allow = self.address.allow
        try:
            if allow is None:
                recv = sock.recv
                for _ in range(MAX_BATCH):
                    append(RawPacket(clock(), recv(READ_BUFFER)))
            else:
                recvfrom = sock.recvfrom
                for _ in range(MAX_BATCH):
                    data, sender = recvfrom(READ_BUFFER)
                    if sender[0] in allow:
                        append(RawPacket(clock(), data))
                    else:
                        self._reject(sender, clock())
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:
            pass
        if out:
            counters = self.counters
            counters["datagrams"] += len(out)
            size = sum([len(p.data) for p in out])
            counters["bytes"] += size
            if size >= READ_BUFFER:
                self._oversize(out)
        return out

    def _reject(self, sender, host_time_ns: int) -> None:
        self.counters["rejected_senders"] += 1
        seen = self._seen_rejected
        if sender[0] in seen or len(seen) > MAX_REJECTED_REPORTED:
            return
        seen.add(sender[0])
        if len(seen) > MAX_REJECTED_REPORTED:
            self.event(host_time_ns, "rejected-sender", self.kind,
                       f"datagrams from more than {MAX_REJECTED_REPORTED} addresses not in allow= are dropped; "
                       f"further senders are counted in rejected_senders only")  # fmt: skip
        else:
            self.event(host_time_ns, "rejected-sender", self.kind,
                       f"datagrams from {sender[0]}:{sender[1]} are not in allow= and are dropped")

    def _oversize(self, packets: list[RawPacket]) -> None:
        big = [p for p in packets if len(p.data) >= READ_BUFFER]
        if big and not self.counters["oversize"]:
            self.event(big[0].host_time_ns, "oversize", self.kind,
                       f"a datagram filled the {READ_BUFFER}-byte read buffer and may be cut (counted in oversize)")
        self.counters["oversize"] += len(big)

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
