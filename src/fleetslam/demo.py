"""The demo as a real deployment on one machine: a cloud process and one process per robot,
talking Zenoh over loopback. The demo then asks the cloud to merge, scores the run against
ground truth (the cloud never sees ground truth) and writes summary.json."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

from fleetslam.cloud.coordination.coordination_service import INSTALL_HINT, EtcdService, etcd_binary
from fleetslam.config import load_config
from fleetslam.datasets.recording import open_source
from fleetslam.edge.report import EXIT_INCOMPLETE
from fleetslam.evaluation.fleet import score_fleet
from fleetslam.launch import (CloudClient, free_endpoint, start_cloud, start_robot, start_router,
                              start_worker, stop, stop_all)
from fleetslam.outputs import (ROBOT_REPORT, add_deployment, add_robot_reports, map_groups,
                               write_summary)
from fleetslam.progress import Progress
from fleetslam.transport.certs import make_lab


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def _await_workers(client: CloudClient, workers: int, timeout_s: float) -> None:
    """Until the cloud answers, and with workers, until every one of them does."""
    deadline = time.monotonic() + timeout_s
    while True:
        answered = client.status(timeout=max(deadline - time.monotonic(), 1.0))["answered"]
        if len(answered) >= workers:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"{len(answered)} of {workers} cloud workers answer after "
                               f"{timeout_s:.0f} s")
        time.sleep(0.5)


def _start_coordination(out: Path, config_path: str | None, certs: Path | None
                        ) -> EtcdService | None:
    """The etcd that fences the workers' ownership of robots, under the run's folder (with
    ``certs``, the lab's <lab>/etcd: mutual TLS); None, said once, when etcd is not
    installed (the workers then agree through liveliness, which a partition can fool)."""
    if etcd_binary() is None:
        print(f"fleetslam demo: etcd is not installed, so the workers' ownership of robots is "
              f"not fenced against partitions; {INSTALL_HINT}", file=sys.stderr)
        return None
    deadline = load_config(config_path).placement.coordination_start_s
    return EtcdService(out / "etcd", deadline, certs=certs).start()


def _check_robots(robots: dict[str, subprocess.Popen], logs: Path, out: Path) -> None:
    """Every robot finished: RuntimeError with the log of one that failed; one whose cloud
    kept less than it sent (exit 3) is said, and the run goes on."""
    failed = {n: p.returncode for n, p in robots.items()
              if p.returncode not in (0, EXIT_INCOMPLETE)}
    if failed:
        name = next(iter(failed))
        raise RuntimeError(f"robot {name} failed (exit {failed[name]}):\n"
                           + _tail(logs / f"{name}.log"))
    for name, p in robots.items():
        if p.returncode == EXIT_INCOMPLETE:
            print(f"fleetslam demo: robot {name}: the cloud did not keep every frame it sent "
                  f"(`incomplete` in {out / name / ROBOT_REPORT})", file=sys.stderr)


# Called with each status while the robots run, and the worker processes (a benchmark kills
# one).
Watch = Callable[[dict[str, Any], list[subprocess.Popen]], None]


def _connections(out: Path, names: list[str], secure: bool, zenoh_config: str | None
                 ) -> tuple[str, dict[str, str | None], Path | None]:
    """The endpoint, each process's Zenoh config and the etcd's TLS folder: over TLS, a lab
    made for this run in ``out/tls`` (unless a Zenoh config file says how to connect)."""
    endpoint = free_endpoint()
    configs: dict[str, str | None] = {name: zenoh_config
                                      for name in ["cloud", "client", "worker", *names]}
    if not secure or zenoh_config is not None:
        return endpoint, configs, None
    lab = make_lab(out / "tls", ["localhost", "127.0.0.1"], names)
    etcd_certs = lab.pop("etcd")
    return (endpoint.replace("tcp/127.0.0.1", "tls/localhost"),
            {name: str(path) for name, path in lab.items()}, etcd_certs)


def _start_cloud_side(endpoint: str, out: Path, config_path: str | None,
                      cloud_args: list[str] | None, configs: dict[str, str | None],
                      workers: int, etcd: Any) -> tuple[subprocess.Popen, list[subprocess.Popen]]:
    """One cloud process; or, with ``workers`` > 1, a Zenoh router and that many workers
    (placed by ``etcd`` if given)."""
    logs = out / "logs"
    if workers <= 1:
        return start_cloud(endpoint, out, logs / "cloud.log", config_path, extra=cloud_args,
                           zenoh_config=configs["cloud"]), []
    worker_args = list(cloud_args or [])
    if etcd is not None:
        worker_args += ["--coordination", etcd.endpoint]
        if etcd.certs is not None:
            worker_args += ["--coordination-certs", str(etcd.certs)]
    router = start_router(endpoint, logs / "router.log", configs["cloud"])
    return router, [start_worker(endpoint, f"w{i}", out, logs / f"w{i}.log", config_path,
                                 extra=worker_args, zenoh_config=configs["worker"])
                    for i in range(workers)]


def _follow_robots(client: CloudClient, robots: dict[str, subprocess.Popen], logs: Path,
                   timeout_s: float, progress: Progress, watch: Watch | None,
                   cloud_workers: list[subprocess.Popen]) -> None:
    """Until every robot process ends: the cloud's status as progress (and to ``watch``);
    a robot that failed, or robots past ``timeout_s``, raise."""
    deadline = time.monotonic() + timeout_s
    while any(p.poll() is None for p in robots.values()):
        if time.monotonic() > deadline:
            raise RuntimeError(f"robots still running after {timeout_s:.0f} s")
        for name, p in robots.items():
            if p.poll() not in (None, 0, EXIT_INCOMPLETE):
                raise RuntimeError(f"robot {name} failed (exit {p.returncode}):\n"
                                   + _tail(logs / f"{name}.log"))
        try:
            status = client.status(timeout=5.0)
            progress.update(sum(r["frames"] for r in status["robots"].values()),
                            f"map groups: {map_groups(status.get('merge'))}")
            if watch is not None:
                watch(status, cloud_workers)
        except TimeoutError:
            pass
        time.sleep(0.5)


def _say_cloud_exits(cloud: subprocess.Popen, cloud_workers: list[subprocess.Popen],
                     logs: Path) -> None:
    """After a failure: each cloud process that exited, with its log's tail."""
    for name, p in [("cloud", cloud)] + [(f"w{i}", w) for i, w in enumerate(cloud_workers)]:
        if p.poll() is not None:
            log = logs / ("router.log" if name == "cloud" and cloud_workers else f"{name}.log")
            print(f"{name} exited ({p.returncode}):\n" + _tail(log), file=sys.stderr)


def run_demo(sources: list[str], out: Path, offload_at: str, config_path: str | None,
             link_args: list[str] | None = None, show_progress: bool = True,
             timeout_s: float = 1800.0, zenoh_config: str | None = None,
             secure: bool = True, cloud_args: list[str] | None = None,
             workers: int = 1,
             watch: Watch | None = None,
             coordination: bool = True) -> dict[str, Any]:
    """Cloud and robots as processes on loopback. ``secure``: over TLS, with a lab made for
    this run in ``out/tls`` (unless a Zenoh config file says how to connect).
    ``cloud_args``: more options of the cloud process (the live view's --view, --save).
    ``workers`` > 1: a Zenoh router and that many cloud workers sharing ``out`` as their
    store; the robots connect to the router and the workers share them out. ``watch``: called
    with each status while the robots run, and the worker processes (a benchmark kills one).
    ``coordination``: the workers are placed by an etcd started for the run (else by Zenoh
    liveliness alone: benchmarks compare the two)."""
    started = time.perf_counter()
    out.mkdir(parents=True, exist_ok=False)
    names = [f"r{i}" for i in range(len(sources))]
    endpoint, configs, etcd_certs = _connections(out, names, secure, zenoh_config)
    logs = out / "logs"
    etcd = _start_coordination(out, config_path, etcd_certs) \
        if workers > 1 and coordination else None
    cloud, cloud_workers = _start_cloud_side(endpoint, out, config_path, cloud_args, configs,
                                             workers, etcd)
    robots: dict[str, Any] = {}
    client = None
    try:
        client = CloudClient(endpoint, zenoh_config=configs["client"])
        _await_workers(client, workers, 60.0)
        for name, source in zip(names, sources):
            robots[name] = start_robot(endpoint, name, source, offload_at, logs / f"{name}.log",
                                       out / name / ROBOT_REPORT, config_path,
                                       link_args, configs[name])
        sequences = {name: open_source(source) for name, source in zip(names, sources)}
        total = sum(len(s) for s in sequences.values())
        progress = Progress(f"cloud tracking {len(names)} robots ({endpoint})", total,
                            enabled=show_progress)
        _follow_robots(client, robots, logs, timeout_s, progress, watch, cloud_workers)
        _check_robots(robots, logs, out)
        progress.update(total)
        summary = client.merge()
    except BaseException:
        for p in robots.values():
            stop(p, 5.0)
        _say_cloud_exits(cloud, cloud_workers, logs)
        raise
    finally:
        if client is not None:
            client.close()
        stop_all([*cloud_workers, cloud])
        if etcd is not None:
            etcd.stop()
    summary.pop("outputs", None)  # where the cloud wrote them: ``out``
    score_fleet(summary, out, sequences)  # ground truth, read only now
    add_robot_reports(summary, out)
    add_deployment(summary, time.perf_counter() - started, endpoint,
                   processes=1 + len(cloud_workers) + len(robots), workers=max(workers, 1),
                   offload_at=offload_at, link=link_args or [])
    write_summary(out, summary)
    return summary
