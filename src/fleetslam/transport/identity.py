"""Whose certificate a Zenoh config file connects with: the common name the cloud's access
control knows a client by (access_control.py). Read here, on the robot, because the access
control's refusal is silent: Zenoh drops a denied message and tells no one.

A robot's install has no X.509 library (cryptography is the cloud's), and the common name
is all it needs: the certificate's DER is walked to its subject (RFC 5280, section 4.1).
"""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

_COMMON_NAME = bytes([0x06, 0x03, 0x55, 0x04, 0x03])  # OID 2.5.4.3, DER-encoded
_PEM = re.compile(rb"-----BEGIN CERTIFICATE-----(.+?)-----END CERTIFICATE-----", re.S)


def _element(der: bytes, at: int) -> tuple[int, int, int]:
    """(tag, start of content, end of content) of the DER element at ``at``."""
    tag, length = der[at], der[at + 1]
    at += 2
    if length & 0x80:
        n = length & 0x7F
        length = int.from_bytes(der[at:at + n], "big")
        at += n
    if at + length > len(der):
        raise ValueError("truncated DER")
    return tag, at, at + length


def _children(der: bytes, start: int, end: int) -> list[tuple[int, int, int]]:
    out = []
    while start < end:
        element = _element(der, start)
        out.append(element)
        start = element[2]
    return out


def subject_common_name(der: bytes) -> str | None:
    """The subject's common name of a DER certificate (None: it has none)."""
    _, start, end = _element(der, 0)  # Certificate
    _, start, end = _children(der, start, end)[0]  # TBSCertificate
    fields = _children(der, start, end)
    if fields[0][0] == 0xA0:  # [0] version, explicit
        fields = fields[1:]
    _, start, end = fields[4]  # serial, signature, issuer, validity, subject
    for _, set_start, set_end in _children(der, start, end):  # RelativeDistinguishedName
        for _, at, stop in _children(der, set_start, set_end):  # AttributeTypeAndValue
            if der[at:at + len(_COMMON_NAME)] == _COMMON_NAME:
                _, value_start, value_end = _element(der, at + len(_COMMON_NAME))
                return der[value_start:value_end].decode("utf-8", "replace")
    return None


def certificate_name(zenoh_config: str) -> tuple[str, str] | None:
    """(the client certificate's path, its common name) that the Zenoh config file at
    ``zenoh_config`` connects with; None when it names no certificate or it cannot be
    read (Zenoh says so itself when it opens the session)."""
    import zenoh  # here: the CLI checks a robot's identity; nothing else loads Zenoh for it

    try:
        tls = json.loads(zenoh.Config.from_file(str(zenoh_config)).get_json(
            "transport/link/tls")) or {}
        path = tls.get("connect_certificate")
        if not path:
            return None
        pem = _PEM.search(Path(path).read_bytes())
        if pem is None:
            return None
        name = subject_common_name(base64.b64decode(b"".join(pem.group(1).split())))
    except (zenoh.ZError, OSError, ValueError, IndexError):
        return None
    return (path, name) if name is not None else None
