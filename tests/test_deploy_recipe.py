"""The README's deployment recipe, run as written on loopback: its commands are read from the README
(the block after the ``deploy-recipe`` marker) and run as separate OS processes — a Zenoh router, the
cloud and edge daemons, ``driveby replay`` of a small simulated log set, then ``driveby status`` and
``driveby export`` — with ``HUB`` → ``127.0.0.1`` and a free port for 7447. Every pass must be
acknowledged, with no segment rejected, and the daemons must say what they do (start, connection,
peers coming and going) and refuse an id that is already live. Waits are on output lines or process exits, each with a generous timeout."""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pyarrow.parquet as pq

from shared.transport import free_port

ROOT = Path(__file__).resolve().parents[1]
MARKER = "<!-- deploy-recipe:"
DAEMONS = ("router", "cloud", "edge")  # long-running: started in the background, stopped at the end
STARTUP_S = 180.0  # a daemon's first start compiles numba kernels into the cache on a loaded 2-core machine
COMMAND_S = 600.0  # simulation, replay and export on a loaded 2-core machine


def recipe() -> list[list[str]]:
    """The README recipe's commands, as argument lists (comments dropped)."""
    text = (ROOT / "README.md").read_text()
    start = text.index(MARKER)
    block = text[text.index("```bash\n", start) + len("```bash\n"):]
    block = block[: block.index("```")]
    return [shlex.split(line, comments=True) for line in block.splitlines() if line.strip()]


def test_the_readme_recipe_is_what_this_test_runs():
    cmds = recipe()
    assert [c[:2] for c in cmds] == [["driveby", "sim"], ["driveby", "router"], ["driveby", "cloud"],
                                     ["driveby", "edge"], ["driveby", "replay"], ["driveby", "status"],
                                     ["driveby", "export"]]
    nets = {c[c.index("--net") + 1] for c in cmds if "--net" in c}
    assert len(nets) == 1, "one --net for every command of a deployment"
    sites = {c[c.index("--site") + 1] for c in cmds if "--site" in c}
    assert sites == {"site.toml"}, "one site.toml for every daemon"


class Process:
    """A background process whose merged output is collected line by line, waited on by content."""

    def __init__(self, argv: list[str], cwd: Path, log: Path):
        self.log = log
        self.lines: list[str] = []
        self.changed = threading.Condition()
        self.proc = subprocess.Popen(argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     stdin=subprocess.DEVNULL, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        with self.proc.stdout, open(self.log, "w") as out:
            for line in self.proc.stdout:
                out.write(line)
                with self.changed:
                    self.lines.append(line.rstrip("\n"))
                    self.changed.notify_all()
        with self.changed:
            self.changed.notify_all()

    def wait_for(self, pattern: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        with self.changed:
            while True:
                hit = next((ln for ln in self.lines if re.search(pattern, ln)), None)
                if hit is not None:
                    return hit
                left = deadline - time.monotonic()
                assert left > 0 and self.proc.poll() is None, \
                    f"no line matching {pattern!r} (exit {self.proc.poll()}): {self.lines[-5:]}"
                self.changed.wait(min(left, 1.0))

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(60.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()


def _argv(cmd: list[str], port: int) -> list[str]:
    """``driveby ...`` as this interpreter's ``python -m simfleet.cli ...`` (the same entry point, without
    relying on PATH), with the hub on loopback at ``port``."""
    assert cmd[0] == "driveby"
    sub = {"tcp/HUB:7447": f"tcp/127.0.0.1:{port}", "tcp/0.0.0.0:7447": f"tcp/127.0.0.1:{port}"}
    return [sys.executable, "-m", "simfleet.cli", *(sub.get(a, a) for a in cmd[1:])]


def _run(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    res = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=COMMAND_S, stdin=subprocess.DEVNULL)
    assert res.returncode == 0 and "Traceback" not in res.stderr, (argv, res.returncode, res.stdout, res.stderr)
    return res


def test_the_readme_deployment_recipe_runs_as_written(tmp_path):
    cmds = {c[1]: c for c in recipe()}
    port = free_port()
    work = tmp_path
    _run(_argv(cmds["sim"], port), work)
    (work / "site.toml").write_bytes((work / "sim" / "site.toml").read_bytes())  # "copy it to every machine"
    passes = len(list((work / "sim" / "logs").glob("*.parquet")))
    assert passes == int(cmds["sim"][cmds["sim"].index("--passes") + 1])
    procs: dict[str, Process] = {}
    try:
        procs["router"] = Process(_argv(cmds["router"], port), work, work / "router.log")
        procs["router"].wait_for(r"^ready ", STARTUP_S)
        procs["cloud"] = Process(_argv(cmds["cloud"], port), work, work / "cloud.log")
        procs["edge"] = Process(_argv(cmds["edge"], port), work, work / "edge.log")
        for me, other in (("cloud", "edge/edge-1"), ("edge", "cloud/cloud-1")):
            procs[me].wait_for(rf"{me}/{me}-1 started: net city, .*endpoints tcp/127\.0\.0\.1:{port}", STARTUP_S)
            procs[me].wait_for(rf"{me}/{me}-1 connected to router ", STARTUP_S)
            procs[me].wait_for(rf"peer {other} is up", STARTUP_S)
            procs["router"].wait_for(rf"router: {me}/{me}-1 on net city is up", STARTUP_S)

        replayed = _run(_argv(cmds["replay"], port), work)
        assert f"{passes}/{passes} passes acknowledged" in replayed.stdout, replayed.stdout
        assert "left" in replayed.stderr or "acknowledged in" in replayed.stderr  # the progress line

        shown = _run(_argv(cmds["status"], port), work)
        assert "cloud cloud-1 (net city)" in shown.stdout, shown.stdout
        assert ", settled;" in shown.stdout, shown.stdout  # --wait: the export below is the settled one
        body = json.loads(_run([*_argv(cmds["status"], port), "--json"], work).stdout)
        # A pass the replay published again (no ack within its resend time: a loaded machine) comes back
        # as duplicates, which the cloud recognises and counts; any other rejection is a defect.
        assert body["stats"]["passes_complete"] >= passes and set(body["stats"]["rejected"]) <= {"duplicate"}, body
        assert body["passes"] == passes and len(body["vehicles"]) == 4, body

        exported = _run(_argv(cmds["export"], port), work)
        assert f"{body['stats']['accepted']} segments accepted" in exported.stdout, exported.stdout
        out = work / cmds["export"][cmds["export"].index("--out") + 1]
        profile = pq.read_table(out / "profile.parquet")
        assert profile.num_rows > 0
        assert (out / "roughness.parquet").exists() and (out / "vehicles.parquet").exists()
        assert len(set(pq.read_table(out / "vehicles.parquet").column("vehicle_id").to_pylist())) == 4

        # A second cloud with a live id refuses to start; a daemon that goes is noticed.
        twin_argv = _argv(cmds["cloud"], port)
        if "--state" in twin_argv:  # its own state directory: only the id is shared
            twin_argv[twin_argv.index("--state") + 1] = str(work / "twin")
        twin = subprocess.run(twin_argv, cwd=work, capture_output=True, text=True, timeout=COMMAND_S,
                              stdin=subprocess.DEVNULL)
        assert twin.returncode == 1 and twin.stderr.strip().count("\n") == 0, twin.stderr
        assert "cloud-1" in twin.stderr and "already live" in twin.stderr, twin.stderr
        assert procs.pop("edge").stop() == 0
        procs["cloud"].wait_for(r"peer edge/edge-1 is gone", STARTUP_S)
    finally:
        codes = {name: p.stop() for name, p in reversed(list(procs.items()))}
    assert codes == {"router": 0, "cloud": 0}, codes
