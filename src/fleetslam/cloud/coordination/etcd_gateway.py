"""A small synchronous etcd v3 client over etcd's JSON gateway (``/v3/kv/...``), standard
library only.

Why not a gRPC client: the workers are threaded, not asyncio (``aetcd`` would need an event
loop thread, and brings grpcio + protobuf to the cloud install); ``etcd3`` is unmaintained
and does not import with today's protobuf; and a grant transaction on loopback takes ~2 ms
through the gateway against ~1.3 ms with aetcd (bench/etcd_clients.py), nothing beside a
lease of seconds. Only what ownership and the fenced store need is here: put, range,
delete, txn, lease grant, keepalive and revoke, and a watch of a prefix. Keys and values are
bytes on our side, base64 on the wire; int64s come back as JSON strings.

One HTTP connection per thread (kept alive); every request has a timeout, and a failure is
an :class:`EtcdError` saying what was asked of which endpoint.
"""

from __future__ import annotations

import base64
import http.client
import json
import logging
import socket
import ssl
import threading
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

log = logging.getLogger("fleetslam.coordination")


class EtcdError(RuntimeError):
    pass


class LeaseExpired(EtcdError):
    """etcd says the lease is gone: whatever was attached to it has been deleted."""


def b64(data: bytes | str) -> str:
    return base64.b64encode(data.encode() if isinstance(data, str) else data).decode()


def unb64(text: str) -> bytes:
    return base64.b64decode(text)


def prefix_end(prefix: bytes) -> bytes:
    """The range end that selects every key starting with ``prefix`` (etcd's convention)."""
    end = bytearray(prefix)
    while end:
        if end[-1] < 0xFF:
            end[-1] += 1
            return bytes(end)
        end.pop()
    return b"\0"


@dataclass(frozen=True)
class KeyValue:
    key: bytes
    value: bytes
    create_revision: int
    mod_revision: int
    version: int
    lease: int

    @staticmethod
    def from_json(kv: dict[str, Any]) -> "KeyValue":
        return KeyValue(unb64(kv["key"]), unb64(kv.get("value", "")),
                        int(kv.get("create_revision", 0)), int(kv.get("mod_revision", 0)),
                        int(kv.get("version", 0)), int(kv.get("lease", 0)))


# -- the pieces of a transaction (etcd's Compare and RequestOp, as the gateway spells them) --

def compare(key: bytes | str, target: str, value: int | bytes, result: str = "EQUAL",
            range_end: bytes | None = None) -> dict[str, Any]:
    """``target``: VERSION, CREATE, MOD, VALUE or LEASE; ``result``: EQUAL, GREATER, LESS,
    NOT_EQUAL. A missing key has version, create and mod revision and lease 0.
    ``range_end``: every key of [key, range_end) must pass (an empty range passes as a
    missing key)."""
    field = {"VERSION": "version", "CREATE": "create_revision", "MOD": "mod_revision",
             "LEASE": "lease", "VALUE": "value"}[target]
    operand = b64(value) if target == "VALUE" else str(value)
    request = {"key": b64(key), "target": target, "result": result, field: operand}
    if range_end is not None:
        request["range_end"] = b64(range_end)
    return request


def put_op(key: bytes | str, value: bytes | str, lease: int = 0) -> dict[str, Any]:
    request: dict[str, Any] = {"key": b64(key), "value": b64(value)}
    if lease:
        request["lease"] = str(lease)
    return {"request_put": request}


def range_op(key: bytes | str) -> dict[str, Any]:
    return {"request_range": {"key": b64(key)}}


def delete_op(key: bytes | str) -> dict[str, Any]:
    return {"request_delete_range": {"key": b64(key)}}


@dataclass(frozen=True)
class TxnResult:
    succeeded: bool
    revision: int
    responses: list[dict[str, Any]]

    def ranged(self, index: int) -> list[KeyValue]:
        """The key-values of the ``index``-th operation (a range)."""
        body = self.responses[index].get("response_range", {})
        return [KeyValue.from_json(kv) for kv in body.get("kvs", [])]


@dataclass(frozen=True)
class EtcdTls:
    """The coordination service's TLS material as ``fleetslam certs`` writes it
    (``<lab>/etcd``): its CA, and the client certificate and key the workers present
    (etcd runs with --client-cert-auth: nothing without a certificate of this CA gets in)."""

    folder: Path

    @staticmethod
    def from_folder(folder: str | Path) -> "EtcdTls":
        tls = EtcdTls(Path(folder))
        missing = [p.name for p in (tls.ca, tls.cert, tls.key) if not p.is_file()]
        if missing:
            raise ValueError(f"{folder}: not the coordination service's TLS folder of a "
                             f"fleetslam lab (no {', '.join(missing)}; `fleetslam certs` "
                             f"writes it as <lab>/etcd)")
        return tls

    @property
    def ca(self) -> Path:
        return self.folder / "ca.pem"

    @property
    def cert(self) -> Path:
        return self.folder / "client.pem"

    @property
    def key(self) -> Path:
        return self.folder / "client.key"

    def context(self) -> ssl.SSLContext:
        """A client's: etcd's certificate checked against the CA, ours presented."""
        context = ssl.create_default_context(cafile=str(self.ca))
        context.load_cert_chain(str(self.cert), str(self.key))
        return context


# DSCP EF (expedited forwarding, RFC 3246) in the IP header, and the kernel's interactive
# priority (band 0 of pfifo_fast / prio qdiscs): a lease's keepalives go ahead of bulk
# traffic wherever the network honours either (a worker's robots' frames share its link).
EXPEDITED_TOS = 0xB8
EXPEDITED_PRIORITY = 6  # TC_PRIO_INTERACTIVE, the highest allowed without CAP_NET_ADMIN


def _mark_expedited(sock: socket.socket) -> None:
    """Best effort: a network or OS without DSCP still carries the packets."""
    try:
        if sock.family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_TCLASS, EXPEDITED_TOS)
        else:
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, EXPEDITED_TOS)
        # After IP_TOS, which sets the priority from the TOS bits on Linux.
        if hasattr(socket, "SO_PRIORITY"):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_PRIORITY, EXPEDITED_PRIORITY)
    except OSError as exc:
        log.debug("expedited marking refused (%s)", exc)


class _Expedited:
    """A connection whose packets are marked expedited once connected (the handshake is
    not: connections are kept alive, so it is rare)."""

    sock: socket.socket

    def connect(self) -> None:
        super().connect()  # type: ignore[misc]
        _mark_expedited(self.sock)


class _ExpeditedHTTP(_Expedited, http.client.HTTPConnection):
    pass


class _ExpeditedHTTPS(_Expedited, http.client.HTTPSConnection):
    pass


def _opener(endpoint: str, tls: EtcdTls | None, expedited: bool = False
            ) -> Callable[[float | None], http.client.HTTPConnection]:
    """What opens a connection to ``endpoint`` (http://HOST:PORT, or https://HOST:PORT with
    ``tls``) with a given timeout, its packets marked expedited if asked; ValueError if the
    endpoint and ``tls`` do not go together."""
    url = urllib.parse.urlsplit(endpoint)
    if url.scheme not in ("http", "https") or not url.hostname or not url.port:
        raise ValueError(f"etcd endpoint {endpoint!r}: expected http://HOST:PORT or "
                         f"https://HOST:PORT")
    if (url.scheme == "https") != (tls is not None):
        raise ValueError(f"etcd endpoint {endpoint!r}: https needs the coordination "
                         f"service's certificates (--coordination-certs), and they need "
                         f"https")
    host, port = url.hostname, url.port
    if tls is None:
        plain = _ExpeditedHTTP if expedited else http.client.HTTPConnection
        return lambda timeout: plain(host, port, timeout=timeout)
    context = tls.context()
    secure = _ExpeditedHTTPS if expedited else http.client.HTTPSConnection
    return lambda timeout: secure(host, port, timeout=timeout, context=context)


class EtcdClient:
    def __init__(self, endpoint: str, timeout_s: float = 2.0, tls: EtcdTls | None = None,
                 expedited: bool = False) -> None:
        """``endpoint``: http://HOST:PORT of an etcd member, or https://HOST:PORT with
        ``tls`` (the lab's coordination certificates). ``expedited``: its packets marked
        to go ahead of bulk traffic (a lease's keepalives)."""
        self.endpoint = endpoint
        self._open = _opener(endpoint, tls, expedited)
        self.timeout_s = timeout_s
        self.tls = tls
        self.cluster_id: str | None = None  # as etcd's last answer said
        self._local = threading.local()

    def _connection(self) -> http.client.HTTPConnection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._open(self.timeout_s)
            self._local.conn = conn
        return conn

    def close(self) -> None:
        """This thread's connection (others close with their threads)."""
        conn = getattr(self._local, "conn", None)
        if conn is not None:
            conn.close()
            self._local.conn = None

    def call(self, path: str, body: dict[str, Any], timeout_s: float | None = None
             ) -> dict[str, Any]:
        """POST ``body`` to ``/v3/<path>``; the reply's JSON. EtcdError if etcd cannot be
        reached within the timeout or answers with an error."""
        data = json.dumps(body).encode()
        for attempt in (1, 2):
            conn = self._connection()
            reused = conn.sock is not None
            conn.timeout = timeout_s or self.timeout_s
            if conn.sock is not None:
                conn.sock.settimeout(conn.timeout)
            try:
                conn.request("POST", f"/v3/{path}", data, {"Content-Type": "application/json"})
                reply = conn.getresponse()
                text = reply.read()
                break
            except (OSError, http.client.HTTPException) as exc:
                conn.close()  # a half-read reply must not be taken for the next one's
                # A kept-alive connection the server had closed: once more on a new one
                # (our transactions are safe to repeat: ownership.grant adopts its own key).
                if attempt == 1 and reused and isinstance(exc, (
                        http.client.RemoteDisconnected, BrokenPipeError, ConnectionResetError)):
                    continue
                raise EtcdError(f"etcd {self.endpoint} /v3/{path}: "
                                f"{exc or type(exc).__name__}") from None
        try:
            answer = json.loads(text)
        except ValueError:
            raise EtcdError(f"etcd {self.endpoint} /v3/{path}: HTTP {reply.status}, not JSON: "
                            f"{text[:200]!r}") from None
        if reply.status != 200 or "error" in answer:
            message = answer.get("message") or answer.get("error") or answer
            raise EtcdError(f"etcd {self.endpoint} /v3/{path}: HTTP {reply.status}: {message}")
        cluster = (answer.get("header") or {}).get("cluster_id")
        if cluster is not None:
            self.cluster_id = str(cluster)
        return answer

    def cluster(self) -> str:
        """etcd's cluster id: a new one is a new history (an etcd wiped and started again
        counts its revisions, so epochs, from 1 again)."""
        self.call("kv/range", {"key": b64("\0")})
        assert self.cluster_id is not None
        return self.cluster_id

    # -- keys ---------------------------------------------------------------------------------

    def put(self, key: bytes | str, value: bytes | str, lease: int = 0) -> int:
        """The revision of the write."""
        body = put_op(key, value, lease)["request_put"]
        return int(self.call("kv/put", body)["header"]["revision"])

    def get(self, key: bytes | str) -> KeyValue | None:
        kvs = self.call("kv/range", {"key": b64(key)}).get("kvs", [])
        return KeyValue.from_json(kvs[0]) if kvs else None

    def get_prefix(self, prefix: bytes | str) -> list[KeyValue]:
        return self.get_prefix_at(prefix)[0]

    def get_prefix_at(self, prefix: bytes | str) -> tuple[list[KeyValue], int]:
        """Every key under ``prefix`` and the revision they were read at (a snapshot)."""
        raw = prefix.encode() if isinstance(prefix, str) else prefix
        answer = self.call("kv/range", {"key": b64(raw), "range_end": b64(prefix_end(raw))})
        return ([KeyValue.from_json(kv) for kv in answer.get("kvs", [])],
                int(answer["header"]["revision"]))

    def delete(self, key: bytes | str) -> int:
        """How many keys were deleted."""
        return int(self.call("kv/deleterange", {"key": b64(key)}).get("deleted", 0))

    def txn(self, compares: list[dict[str, Any]], success: list[dict[str, Any]],
            failure: list[dict[str, Any]] | None = None) -> TxnResult:
        answer = self.call("kv/txn", {"compare": compares, "success": success,
                                      "failure": failure or []})
        return TxnResult(bool(answer.get("succeeded", False)),
                         int(answer["header"]["revision"]), answer.get("responses", []))

    # -- leases -------------------------------------------------------------------------------

    def lease_grant(self, ttl_s: int) -> tuple[int, int]:
        """A new lease: (its id, the TTL etcd granted, which may be longer than asked)."""
        answer = self.call("lease/grant", {"TTL": ttl_s})
        return int(answer["ID"]), int(answer["TTL"])

    def lease_keepalive(self, lease: int, timeout_s: float | None = None) -> int:
        """Renew the lease; the TTL it has again. EtcdError if it has expired (TTL <= 0)."""
        result = self.call("lease/keepalive", {"ID": str(lease)}, timeout_s).get("result", {})
        ttl = int(result.get("TTL", 0))
        if ttl <= 0:
            raise LeaseExpired(f"etcd {self.endpoint}: lease {lease:x} has expired")
        return ttl

    def lease_revoke(self, lease: int) -> None:
        self.call("lease/revoke", {"ID": str(lease)})


# -- watching -------------------------------------------------------------------------------

@dataclass(frozen=True)
class Event:
    deleted: bool  # a delete (or the key's lease expired); else a put
    kv: KeyValue


class Watch:
    """The events under ``prefix`` from etcd's watch stream, to ``on_events`` on a thread of
    its own (a worker hears at once that a robot's owner key went with its lease, instead of
    asking every so often). A broken stream is opened again from the revision after the last
    event seen, so nothing is missed while etcd keeps its history."""

    def __init__(self, endpoint: str, prefix: bytes | str,
                 on_events: Callable[[list[Event]], None], start_revision: int = 0,
                 retry_s: float = 0.5, tls: EtcdTls | None = None,
                 on_reset: Callable[[], None] | None = None) -> None:
        """``on_reset``: called when etcd's history was reset under the watch (an etcd wiped
        and started again counts revisions from 1: the events from here on have revisions
        below those heard before, and what was known of the prefix is void)."""
        self.endpoint = endpoint
        self._open = _opener(endpoint, tls)
        self._on_reset = on_reset or (lambda: None)
        self._prefix = prefix.encode() if isinstance(prefix, str) else prefix
        self._on_events = on_events
        self.next_revision = start_revision
        self.retry_s = retry_s
        self.created = threading.Event()  # the stream is open (events from now on arrive)
        self._closed = threading.Event()
        self._conn: http.client.HTTPConnection | None = None
        self._thread = threading.Thread(target=self._run, name="etcd-watch", daemon=True)

    def start(self) -> "Watch":
        self._thread.start()
        return self

    def close(self, deadline_s: float = 2.0) -> None:
        self._closed.set()
        conn = self._conn
        if conn is not None and conn.sock is not None:
            try:  # wakes the thread blocked reading the stream
                conn.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self._thread.join(deadline_s)

    def _run(self) -> None:
        while not self._closed.is_set():
            try:
                self._stream()
            except (OSError, http.client.HTTPException, ValueError, EtcdError) as exc:
                if not self._closed.is_set():
                    log.warning("etcd watch of %r at %s broke (%s); again in %g s",
                                self._prefix, self.endpoint, exc, self.retry_s)
            self.created.clear()
            self._closed.wait(self.retry_s)

    def _stream(self) -> None:
        # No read timeout: a quiet prefix sends nothing for as long as it likes; close()
        # shuts the socket to end the read.
        conn = self._open(None)
        self._conn = conn
        try:
            request = {"key": b64(self._prefix), "range_end": b64(prefix_end(self._prefix))}
            if self.next_revision:
                request["start_revision"] = str(self.next_revision)
            conn.request("POST", "/v3/watch", json.dumps({"create_request": request}).encode(),
                         {"Content-Type": "application/json"})
            reply = conn.getresponse()
            if reply.status != 200:
                raise EtcdError(f"etcd {self.endpoint} /v3/watch: HTTP {reply.status}")
            while not self._closed.is_set():
                line = reply.readline()
                if not line:
                    raise EtcdError(f"etcd {self.endpoint} /v3/watch: the stream ended")
                if not line.strip():
                    continue
                answer = json.loads(line)
                if "error" in answer:
                    raise EtcdError(f"etcd {self.endpoint} /v3/watch: {answer['error']}")
                result = answer.get("result", {})
                if result.get("canceled"):
                    compacted = int(result.get("compact_revision", 0))
                    if compacted:  # history gone: from the oldest etcd still has
                        log.warning("etcd watch of %r: history before revision %d compacted",
                                    self._prefix, compacted)
                        self.next_revision = compacted
                    raise EtcdError(f"etcd {self.endpoint} /v3/watch: canceled "
                                    f"({result.get('cancel_reason', 'no reason given')})")
                if result.get("created"):
                    now = int((result.get("header") or {}).get("revision", 0))
                    if self.next_revision > now + 1:
                        log.error("etcd at %s has revision %d, the watch of %r had heard up "
                                  "to %d: etcd's history was reset; what was known of it is "
                                  "read again", self.endpoint, now, self._prefix,
                                  self.next_revision - 1)
                        self.next_revision = 1  # the new history from its start
                        try:
                            self._on_reset()
                        except Exception:
                            log.exception("etcd watch of %r: the reset's callback failed",
                                          self._prefix)
                        raise EtcdError(f"etcd {self.endpoint} /v3/watch: history reset")
                    self.created.set()
                events = [Event(e.get("type") == "DELETE", KeyValue.from_json(e["kv"]))
                          for e in result.get("events", [])]
                if events:
                    self.next_revision = max(e.kv.mod_revision for e in events) + 1
                    try:
                        self._on_events(events)
                    except Exception:
                        log.exception("etcd watch of %r: the events' callback failed",
                                      self._prefix)
        finally:
            self._conn = None
            conn.close()
