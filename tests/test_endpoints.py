"""Endpoints are checked before Zenoh sees them: one line naming the flag and what is
wrong, at once (no traceback, no retrying until the reach deadline)."""

from __future__ import annotations


import pytest

from fleetslam import cli
from fleetslam.config import load_config


@pytest.mark.parametrize("argv, message", [
    (["cloud", "--listen", "foo", "--out", "{tmp}/store"],
     "--listen 'foo': not PROTOCOL/ADDRESS"),
    (["status", "--connect", ""], "--connect '': not PROTOCOL/ADDRESS"),
    (["robot", "--connect", "garbage", "--id", "r1", "--source", "nowhere"],
     "--connect 'garbage': not PROTOCOL/ADDRESS"),
    (["merge", "--connect", "tls/"], "--connect 'tls/': not PROTOCOL/HOST:PORT"),
    (["merge", "--connect", "tcp/not a host:x"], "port 'x' is not a number in 1..65535"),
    (["merge", "--connect", "tcp/not a host:7447"],
     "'not a host' is not a host name or an IP address"),
    (["merge", "--connect", "tcp/127.0.0.1:70000"], "port '70000' is not a number"),
    (["merge", "--connect", "tcp/[::1x]:7447"], "'[::1x]' is not an IPv6 address"),
    (["merge", "--connect", "tcp/::1:7447"], "an IPv6 address is written in brackets"),
    (["status", "--connect", "tcp/nohost.invalid:7447"], "host 'nohost.invalid' does not "
                                                         "resolve"),
    (["merge", "--connect", "tls/localhost:7447"], "tls needs a Zenoh config file with the "
                                                   "lab's TLS certificates"),
    (["router", "--listen", "tcp/127.0.0.1:7447", "--connect", "udp/host_x:1"],
     "--connect 'udp/host_x:1': 'host_x' is not a host name"),
    (["robot", "--id", "r1", "--source", "ros2:tcp/nohost.invalid:7447"],
     "endpoint 'tcp/nohost.invalid:7447': host 'nohost.invalid' does not resolve"),
])
def test_a_bad_endpoint_fails_at_once_in_one_line(argv, message, tmp_path, capsys):
    code = cli.main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("fleetslam: error: "), err
    # One line: refused before any attempt to connect (each attempt says so on a line).
    assert message in err and err.count("\n") == 1 and "Traceback" not in err, err


def test_a_bad_endpoint_in_the_config_file_names_key_and_file(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text('[transport]\nendpoint = "tcp/cloud:"\n')
    assert cli.main(["--config", str(path), "robot", "--id", "r1", "--source", "x"]) == 2
    assert capsys.readouterr().err == (f"fleetslam: error: {path}: transport.endpoint = "
                                       f"'tcp/cloud:': port '' is not a number in 1..65535\n")


def test_the_config_files_endpoint_that_does_not_resolve_fails_at_once(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text('[transport]\nendpoint = "tcp/nohost.invalid:7447"\n')
    assert cli.main(["--config", str(path), "cloud", "--out", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err  # ends with the resolver's reason, which varies by system
    assert err.startswith(f"fleetslam: error: {path}: transport.endpoint "
                          f"'tcp/nohost.invalid:7447': host 'nohost.invalid' does not resolve (")
    assert err.count("\n") == 1


def test_tls_with_a_zenoh_config_holding_certificates_passes(tmp_path):
    from fleetslam.validation.endpoints import check_endpoint

    lab = tmp_path / "client.json5"
    lab.write_text('{transport: {link: {tls: {root_ca_certificate: "ca.pem"}}}}')
    plain = tmp_path / "plain.json5"
    plain.write_text("{mode: 'client'}")
    assert check_endpoint("tls/localhost:7447", "--connect", str(lab)) == "tls/localhost:7447"
    with pytest.raises(ValueError, match="--connect 'quic/localhost:7447': quic needs"):
        check_endpoint("quic/localhost:7447", "--connect", str(plain))
    assert check_endpoint("unixsock-stream//tmp/z.sock", "--listen") and load_config()


@pytest.fixture
def taken_endpoint():
    """A loopback port a plain socket listens on, as ROS 2's rmw_zenohd holds 7447."""
    import socket

    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        yield f"tcp/127.0.0.1:{holder.getsockname()[1]}"


@pytest.mark.parametrize("command", [["cloud", "--out", "{tmp}/store"], ["router"]])
def test_a_taken_port_is_one_line_naming_port_and_flag_and_leaves_nothing(
        command, taken_endpoint, tmp_path, capsys):
    import multiprocessing

    argv = [a.replace("{tmp}", str(tmp_path)) for a in command] + ["--listen", taken_endpoint]
    before = set(multiprocessing.active_children())
    assert cli.main(argv) == 2
    port = taken_endpoint.rpartition(":")[2]
    assert capsys.readouterr().err == (
        f"fleetslam: error: --listen '{taken_endpoint}': port {port} is taken (another Zenoh "
        f"router? ROS 2's rmw_zenohd uses 7447): choose another with --listen\n")
    assert not (tmp_path / "store").exists()
    assert not set(multiprocessing.active_children()) - before


def test_a_taken_port_in_the_config_file_names_the_setting(taken_endpoint, tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text(f'[transport]\nendpoint = "{taken_endpoint}"\n')
    assert cli.main(["--config", str(path), "cloud", "--out", str(tmp_path / "store")]) == 2
    assert capsys.readouterr().err.startswith(
        f"fleetslam: error: {path}: transport.endpoint '{taken_endpoint}': port ")
    assert not (tmp_path / "store").exists()


def test_a_cloud_whose_port_is_taken_as_it_starts_leaves_no_process(taken_endpoint, tmp_path):
    """Taken after the command line's check (or a caller without one): Zenoh's refusal in
    one line, and the place search and local mapping processes the cloud had started end
    with it (they outlived it, and the search's end was logged as its failure)."""
    import multiprocessing

    from fleetslam.cloud.server import CloudServer
    from fleetslam.config import Config

    before = set(multiprocessing.active_children())
    server = CloudServer(Config(), tmp_path / "store", taken_endpoint)
    with pytest.raises(RuntimeError, match=f"cannot listen on {taken_endpoint}: its port is "
                       r"taken \(another Zenoh router\? ROS 2's rmw_zenohd uses 7447\): "
                       "choose another with --listen$"):
        server.start()
    assert not set(multiprocessing.active_children()) - before

