"""Every wait of a command has a deadline and says what to check: `status` / `merge` give up
after a short default deadline, a TLS refusal is told apart from "nothing listens" (a plain
TCP connection sees the difference; Zenoh itself says only "Timeout!"), and an open session
the cloud never answers (no cloud there, or its access control dropping our messages, which
Zenoh does not report) is hinted at within seconds, for the operator and for a robot."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import HANG_S, TUM_RPY, exact_config, require

from fleetslam.config import Config
from fleetslam.launch import free_endpoint

SRC = Path(__file__).resolve().parents[1] / "src"


def fleetslam(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """The command run to its end; subprocess.TimeoutExpired past HANG_S (a wait the
    command should not have made: the tests give it far longer defaults than their flags)."""
    env = dict(os.environ, PYTHONPATH=str(SRC))
    return subprocess.run([sys.executable, "-m", "fleetslam.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=HANG_S)


def long_waits(tmp_path: Path) -> str:
    """A config file whose deadlines are far beyond HANG_S: a command that ignored its
    --deadline would time out."""
    path = tmp_path / "long-waits.toml"
    path.write_text(f"[transport]\nask_deadline_s = {4 * HANG_S}\n")
    return str(path)


def error_line(done: subprocess.CompletedProcess) -> str:
    """The command's error: its last stderr line, one line, no traceback."""
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    last = done.stderr.splitlines()[-1]
    assert last.startswith("fleetslam: error: ")
    return last


def test_status_and_merge_with_no_cloud_give_up_soon_saying_what_to_check(tmp_path):
    assert Config().transport.ask_deadline_s <= 30  # not the robots' 600 s
    port = free_endpoint().rsplit(":", 1)[1]
    work = tmp_path / "work"
    work.mkdir()
    for command in ("status", "merge"):
        done = fleetslam([command, "--config", long_waits(tmp_path), "--connect",
                          f"tcp/127.0.0.1:{port}", "--deadline", "2"], work)
        assert f"nothing listens at 127.0.0.1:{port} (connection refused): is the cloud " \
               f"running" in error_line(done)
    assert list(work.iterdir()) == []


def test_status_and_merge_say_a_refused_connection_before_their_deadline(tmp_path):
    """Nothing listens: the refusal is the answer, not a wait until --deadline (600 s here;
    the subprocess's 60 s timeout only guards against a hang)."""
    endpoint = free_endpoint()
    for command in ("status", "merge"):
        done = fleetslam([command, "--connect", endpoint, "--deadline", "600"], tmp_path)
        assert done.stderr == (f"fleetslam: error: no cloud at {endpoint}: nothing listens at "
                               f"{endpoint.partition('/')[2]} (connection refused): is the "
                               f"cloud running, and is this its endpoint (--connect)?\n")
        assert done.returncode == 2


@pytest.fixture(scope="module")
def tls_cloud(tmp_path_factory):
    """(endpoint, the lab's Zenoh configs, another lab's): a cloud over mutual TLS with
    access control, robots r1 and r2."""
    from fleetslam.cloud.server import CloudServer
    from fleetslam.transport.certs import make_lab

    tmp = tmp_path_factory.mktemp("tls")
    lab = make_lab(tmp / "lab", ["localhost"], ["r1", "r2"])
    other = make_lab(tmp / "other", ["localhost"], [])
    config = exact_config().with_values({"transport.zenoh_config": str(lab["cloud"])})
    endpoint = free_endpoint().replace("tcp/127.0.0.1", "tls/localhost")
    server = CloudServer(config, tmp / "cloud", endpoint).start()
    yield endpoint, lab, other
    server.close()


def test_a_certificate_of_another_lab_is_told_from_no_cloud(tls_cloud, tmp_path):
    endpoint, _, other = tls_cloud
    done = fleetslam(["status", "--connect", endpoint, "--zenoh-config",
                      str(other["client"]), "--deadline", "4"], tmp_path)
    assert "but refuses a Zenoh session: most likely the TLS handshake: is --zenoh-config " \
           f"{other['client']} from the cloud's lab" in error_line(done)
    # Said on the first failed attempt too, not only at the deadline.
    assert done.stderr.splitlines()[0].startswith(
        f"no cloud answers at {endpoint} yet; retrying for up to 4 s (--deadline, "
        f"transport.ask_deadline_s): something listens")
    # Plain TCP to the TLS listener: "is it a tls/ endpoint".
    done = fleetslam(["status", "--connect", endpoint.replace("tls/", "tcp/"),
                      "--deadline", "2"], tmp_path)
    assert "is it a tls/ endpoint" in error_line(done)


def test_the_operator_asking_with_a_robots_certificate_is_hinted_at_early(tls_cloud, tmp_path):
    endpoint, lab, _ = tls_cloud
    done = fleetslam(["merge", "--config", long_waits(tmp_path), "--connect", endpoint,
                      "--zenoh-config", str(lab["r1"]), "--deadline", "6"], tmp_path)
    told = ("its access control drops our messages, which Zenoh does not report: only the "
            "operator's certificate (client.json5 of the lab) may ask the cloud")
    assert told in error_line(done)
    hint = [line for line in done.stderr.splitlines() if line.startswith(
        f"no answer from the cloud at {endpoint} yet (3 s): ")]
    assert len(hint) == 1 and told in hint[0]
    done = fleetslam(["status", "--connect", endpoint, "--zenoh-config",
                      str(lab["client"]), "--deadline", "10"], tmp_path)
    assert done.returncode == 0 and "workers:" in done.stdout  # the operator is answered
    done = fleetslam(["merge", "--connect", endpoint, "--zenoh-config", str(lab["client"]),
                      "--deadline", "10"], tmp_path)
    # Answered: the cloud says it has nothing to merge yet (no robot finished).
    assert "no robot has finished yet" in done.stderr, done.stderr


def test_a_robot_with_another_robots_certificate_is_hinted_at_early(tls_cloud, tmp_path):
    endpoint, lab, _ = tls_cloud
    (tmp_path / "c.toml").write_text("[transport]\nmax_attempts = 3\n")
    # After 3 hellos, not transport.reach_deadline_s (600 s): fleetslam() times out at HANG_S.
    done = fleetslam(["--quiet", "robot", "--config", "c.toml", "--id", "r1",
                      "--connect", endpoint, "--zenoh-config", str(lab["r2"]),
                      "--source", f"{require(TUM_RPY)}:0-4"], tmp_path)
    told = ("a robot may use only its own keys: is it robot r1's certificate "
            "(robot-r1.json5 of the lab)")
    assert "after 3 hellos" in error_line(done) and told in error_line(done)
    lines = done.stderr.splitlines()
    # At once, before any hello: the certificate its Zenoh config connects with is r2's.
    certificate = (lab["r2"].parent / "r2.pem").resolve()
    assert lines[0] == (f"fleetslam robot r1: warning: --zenoh-config {lab['r2']} connects "
                        f"with the certificate of 'r2' ({certificate}), not of 'r1': a "
                        f"lab's cloud admits a robot's messages "
                        f"only under its own certificate (robot-r1.json5 of the lab) and "
                        f"drops the others unseen")
    hint = [line for line in lines if "WARNING robot r1: no answer to its hello" in line]
    assert len(hint) == 1 and told in hint[0]


def test_the_common_name_is_read_without_an_x509_library(tls_cloud):
    """The robot reads its certificate's name by walking the DER (its install has no
    cryptography): the same name cryptography reads, for each identity of a lab."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    from fleetslam.transport.identity import certificate_name

    _, lab, _ = tls_cloud
    for who in ("r1", "r2", "client", "worker"):
        path, name = certificate_name(str(lab[who]))
        cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
        assert name == cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value
    assert certificate_name(str(lab["cloud"])) is None  # a listener: no client certificate
