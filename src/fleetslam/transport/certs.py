"""A lab's TLS material in one command (``fleetslam certs``): a certificate authority, a
certificate for the cloud (its host names), one per robot (its id as the common name) and
one for the operator's tools, and the Zenoh config files that use them; in ``etcd/`` the
coordination service's (a CA of its own, etcd's server certificate, the workers' client
certificate). TLS is mutual: the
cloud accepts only peers holding a certificate of the lab (Zenoh's ``enable_mtls``), and its
access control lets each certificate use only its own keys (``access_control.py``). The
same command adds robots to an existing lab.

Keys are EC P-256, written owner-readable only. The CA's key stays in the output folder and
is what signs more robots later; keep it off the robots.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from fleetslam.transport.access_control import (
    OPERATOR,
    WORKER,
    check_robot_identity,
    fleet_acl,
)

VALID_DAYS = 825
MANIFEST = "lab.json"  # the lab's hosts and robots: what the cloud's ACL admits


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                       serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    os.chmod(path, 0o600)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "fleetslam lab"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _issue(subject: str, key: ec.EllipticCurvePrivateKey, ca_key: ec.EllipticCurvePrivateKey,
           ca_name: x509.Name, hosts: list[str], usage: list[x509.ObjectIdentifier]
           ) -> x509.Certificate:
    now = datetime.datetime.now(datetime.timezone.utc)
    builder = (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(ca_name)
               .public_key(key.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(now - datetime.timedelta(minutes=5))
               .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.ExtendedKeyUsage(usage), critical=False))
    if hosts:
        names: list[x509.GeneralName] = []
        for host in hosts:
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(host)))
            except ValueError:
                names.append(x509.DNSName(host))
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return builder.sign(ca_key, hashes.SHA256())


def _make_ca(common_name: str) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    now = datetime.datetime.now(datetime.timezone.utc)
    ca_key = _key()
    ca_name = _name(common_name)
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name)
          .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
          .not_valid_before(now - datetime.timedelta(minutes=5))
          .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True,
                                       crl_sign=True, content_commitment=False,
                                       key_encipherment=False, data_encipherment=False,
                                       key_agreement=False, encipher_only=False,
                                       decipher_only=False), critical=True)
          .sign(ca_key, hashes.SHA256()))
    return ca_key, ca


def make_etcd_certs(folder: Path, hosts: list[str]) -> Path:
    """The coordination service's TLS material in ``folder`` (``<lab>/etcd``): a CA of its
    own (so the robots' certificates, of the lab's CA, open nothing of etcd), etcd's server
    certificate for ``hosts`` and the one client certificate the cloud workers present
    (etcd's --client-cert-auth takes only certificates of this CA). Returns ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    ca_key, ca = _make_ca("fleetslam coordination CA")
    _write_key(folder / "ca.key", ca_key)
    _write_cert(folder / "ca.pem", ca)
    server_key, client_key = _key(), _key()
    _write_key(folder / "server.key", server_key)
    # Client use too: etcd's JSON gateway calls etcd's own gRPC with this certificate, and
    # with --client-cert-auth that call must present one (else every request: HTTP 503).
    _write_cert(folder / "server.pem", _issue("fleetslam etcd", server_key, ca_key, ca.subject,
                                              hosts, [ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]))
    _write_key(folder / "client.key", client_key)
    _write_cert(folder / "client.pem", _issue(WORKER, client_key, ca_key, ca.subject, [],
                                              [ExtendedKeyUsageOID.CLIENT_AUTH]))
    return folder


def make_lab(out: Path, hosts: list[str], robots: list[str]) -> dict[str, Path]:
    """Write ca.pem/ca.key, cloud.pem/cloud.key, operator.pem/.key, <robot>.pem/.key, lab.json
    and the Zenoh configs: cloud.json5 (the router: TLS listener and access control),
    client.json5 (the operator's tools), worker.json5 (cloud workers behind the router) and
    robot-<id>.json5. In an existing lab, issue only
    the new robots' certificates (with its CA) and rewrite cloud.json5 to admit them.
    Returns the config files (and the CA) by name."""
    if (out / "ca.key").exists():
        if not robots:
            raise FileExistsError(f"{out / 'ca.key'} exists: a lab has one CA (use another "
                                  f"folder, or name robots to add to this lab)")
        return _add_robots(out, robots)
    if not hosts:
        raise ValueError("the cloud's certificate needs at least one host name or address")
    out.mkdir(parents=True, exist_ok=True)
    ca_key, ca = _make_ca("fleetslam lab CA")
    ca_name = ca.subject
    _write_key(out / "ca.key", ca_key)
    _write_cert(out / "ca.pem", ca)
    cloud_key = _key()
    _write_key(out / "cloud.key", cloud_key)
    _write_cert(out / "cloud.pem", _issue("fleetslam cloud", cloud_key, ca_key, ca_name, hosts,
                                          [ExtendedKeyUsageOID.SERVER_AUTH]))
    _client(out, OPERATOR, "client.json5", ca_key, ca_name)
    _write_manifest(out, {"hosts": hosts, "robots": []})
    _client(out, WORKER, "worker.json5", ca_key, ca_name)
    make_etcd_certs(out / "etcd", hosts)
    return _add_robots(out, robots)


def _add_robots(out: Path, robots: list[str]) -> dict[str, Path]:
    manifest = json.loads((out / MANIFEST).read_text())
    ca_key = serialization.load_pem_private_key((out / "ca.key").read_bytes(), None)
    if not isinstance(ca_key, ec.EllipticCurvePrivateKey):
        raise ValueError(f"{out / 'ca.key'}: not the EC key of a fleetslam lab")
    ca_name = x509.load_pem_x509_certificate((out / "ca.pem").read_bytes()).subject
    for robot in robots:
        check_robot_identity(robot)  # before its files: "operator" would overwrite the tools'
        if robot in manifest["robots"]:
            raise FileExistsError(f"robot {robot} is already in the lab {out}")
        _client(out, robot, f"robot-{robot}.json5", ca_key, ca_name)
        manifest["robots"].append(robot)
    _write_manifest(out, manifest)
    if not (out / "worker.json5").exists():  # a lab made before cloud workers existed
        _client(out, WORKER, "worker.json5", ca_key, ca_name)
    tls_cloud = {"root_ca_certificate": str((out / "ca.pem").resolve()),
                 "listen_private_key": str((out / "cloud.key").resolve()),
                 "listen_certificate": str((out / "cloud.pem").resolve()),
                 "enable_mtls": True}
    # The cloud is the router all clients go through, so its ACL sees every message.
    if not (out / "etcd").exists():  # a lab made before the coordination service's TLS
        make_etcd_certs(out / "etcd", manifest["hosts"])
    files = {"ca": out / "ca.pem", "etcd": out / "etcd",
             "cloud": _config(out / "cloud.json5", "router", tls_cloud,
                              fleet_acl(manifest["robots"])),
             "client": out / "client.json5", "worker": out / "worker.json5"}
    files.update({robot: out / f"robot-{robot}.json5" for robot in manifest["robots"]})
    return files


def _client(out: Path, name: str, config: str, ca_key: ec.EllipticCurvePrivateKey,
            ca_name: x509.Name) -> None:
    """A client certificate whose common name is the identity the ACL knows, and its
    Zenoh config."""
    key = _key()
    _write_key(out / f"{name}.key", key)
    _write_cert(out / f"{name}.pem", _issue(name, key, ca_key, ca_name, [],
                                            [ExtendedKeyUsageOID.CLIENT_AUTH]))
    _config(out / config, "client", {
        "root_ca_certificate": str((out / "ca.pem").resolve()),
        "connect_private_key": str((out / f"{name}.key").resolve()),
        "connect_certificate": str((out / f"{name}.pem").resolve()),
        "enable_mtls": True})


def lab_robots(out: Path) -> list[str]:
    """The robots of the lab in ``out`` (those its cloud's access control admits)."""
    return list(json.loads((out / MANIFEST).read_text())["robots"])


def _write_manifest(out: Path, manifest: dict) -> None:
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")


def _config(path: Path, mode: str, tls: dict[str, str | bool],
            access_control: dict | None = None) -> Path:
    config: dict = {"mode": mode, "scouting": {"multicast": {"enabled": False}},
                    "transport": {"link": {"tls": tls}}}
    if access_control is not None:
        config["access_control"] = access_control
    path.write_text(json.dumps(config, indent=2) + "\n")
    return path
