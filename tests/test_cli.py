"""The ``driveby`` command line: help on every option of every subcommand, and every bad path, file
or argument answered with one line and the same exit code rule (2: the command line is wrong; 1:
what it names cannot be used, or nothing answers), never a traceback. Real subprocesses."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from cloud.daemon import node as cloud_node
from edge import node as edge_node
from shared import transport
from simfleet import cli
from simfleet import node as fleet_node

TIMEOUT_S = 120.0  # a subprocess that imports numba-compiled modules on a loaded 2-core machine


def _parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    """Every parser a user meets: driveby's subcommands, the daemons' own, the router's."""
    out = []
    top = cli.build_parser()
    out.append(("driveby", top))
    for action in top._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                if name not in cli.DAEMONS and name != "router":  # placeholders: the daemons parse their own
                    out.append((f"driveby {name}", sub))
    out += [("driveby cloud", cloud_node.build_parser()), ("driveby edge", edge_node.build_parser()),
            ("driveby fleet", fleet_node.build_parser())]
    router = transport.build_parser("driveby")
    for action in router._actions:
        if isinstance(action, argparse._SubParsersAction):
            out += [(f"driveby {name}", sub) for name, sub in action.choices.items()]
    return out


def test_every_option_of_every_subcommand_has_help():
    parsers = _parsers()
    names = {n for n, _ in parsers}
    assert {"driveby run", "driveby demo", "driveby sim", "driveby cloud", "driveby edge", "driveby fleet",
            "driveby status", "driveby export", "driveby replay", "driveby view", "driveby router"} <= names
    missing = []
    for name, p in parsers:
        for action in p._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            # A subcommand list: each subcommand says what it does (its options are walked as a parser).
            described = action._choices_actions if isinstance(action, argparse._SubParsersAction) else [action]
            missing += [f"{name} {a.option_strings or a.dest}" for a in described
                        if not a.help or a.help == argparse.SUPPRESS or not a.help.strip()]
    assert not missing, f"options without help: {missing}"


def _driveby(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "simfleet.cli", *args], capture_output=True, text=True,
                          timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    (d / "a-file").write_text("not a directory\n")
    (d / "bad.toml").write_text("[[route]\n")
    (d / "logs").mkdir()
    (d / "logs" / "broken.parquet").write_bytes(b"not parquet at all")
    (d / "empty").mkdir()
    return d


# (arguments, exit code, a word the one line must contain); {d}: the fixture's directory, {port}: a free port
CASES = [
    # what the arguments name cannot be used: 1
    (["run", "--logs", "/nonexistent", "--site", "{d}/bad.toml", "--export", "{d}/x"], 1, "bad.toml"),
    (["run", "--logs", "{d}/logs", "--site", "/nonexistent/site.toml", "--export", "{d}/x"], 1, "site.toml"),
    (["demo", "--out", "/proc/nope"], 1, "/proc/nope"),
    (["sim", "road-qc", "--out", "{d}/a-file", "--passes", "1"], 1, "a-file"),
    (["cloud", "--site", "/nonexistent/site.toml"], 1, "site.toml"),
    (["cloud", "--site", "{d}/bad.toml"], 1, "bad.toml"),
    (["edge", "--site", "{d}/bad.toml"], 1, "bad.toml"),
    (["edge", "--spool", "{d}/a-file"], 1, "a-file"),
    (["fleet", "--site", "/nonexistent/site.toml", "--vehicles", "2"], 1, "site.toml"),
    (["router", "--listen", "tls/127.0.0.1:{port}", "--security", "{d}/empty"], 1, "ca.pem"),
    (["status", "--connect", "tcp/127.0.0.1:{port}"], 1, "127.0.0.1"),
    (["export", "--connect", "tcp/127.0.0.1:{port}", "--out", "{d}/out"], 1, "127.0.0.1"),
    (["export", "--connect", "tcp/127.0.0.1:{port}", "--out", "{d}/a-file/out"], 1, "a-file"),
    (["replay", "--connect", "tcp/127.0.0.1:{port}", "--logs", "/nonexistent"], 1, "/nonexistent"),
    (["replay", "--connect", "tcp/127.0.0.1:{port}", "--logs", "{d}/logs"], 1, "broken.parquet"),
    (["replay", "--connect", "tcp/127.0.0.1:{port}", "--logs", "{d}/empty"], 1, "no drive logs"),
    (["view", "{d}/nope.rrd"], 1, "nope.rrd"),
    # the command line itself is wrong: 2
    (["run", "--site", "x.toml", "--export", "x"], 2, "--logs"),
    (["sim", "road-qc", "--out", "{d}/s", "--passes", "0"], 2, "--passes"),
    (["demo", "--passes", "many"], 2, "--passes"),
    (["cloud", "--site", "x.toml", "--net", "a/b"], 2, "net"),
    (["cloud", "--site", "x.toml", "--log-level", "chatty"], 2, "--log-level"),
    (["edge", "--ap-batch", "0"], 2, "--ap-batch"),
    (["edge", "--connect", "127.0.0.1:7447"], 2, "endpoint"),
    (["fleet", "--site", "x.toml", "--vehicles", "0"], 2, "--vehicles"),
    (["status", "--timeout", "soon"], 2, "--timeout"),
    (["status"], 2, "--connect"),
    (["status", "--connect", "tcp/127.0.0.1:7447", "--wait", "-1"], 2, "--wait"),
    (["status", "--connect", "tcp/127.0.0.1:7447", "--cloud", "a/b"], 2, "--cloud"),
    (["export", "--connect", "tcp/127.0.0.1:7447", "--net", "a b", "--out", "x"], 2, "--net"),
    (["replay", "--connect", "localhost", "--logs", "x"], 2, "endpoint"),
    (["export", "--connect", "tcp/127.0.0.1:7447"], 2, "--out"),
    (["replay", "--connect", "tcp/127.0.0.1:7447"], 2, "--logs"),
    (["view"], 2, "FILE"),
]


#: The daemons' cases run in this process, through the daemon's own ``main`` (what ``driveby cloud``
#: hands its command line to): importing a daemon costs seconds, once here instead of once per case.
IN_PROCESS = {"cloud": cloud_node.main, "edge": edge_node.main}


@pytest.mark.parametrize("args, code, word", CASES, ids=[" ".join(c[0][:2]) + f"-{i}" for i, c in enumerate(CASES)])
def test_bad_input_is_one_line_and_a_consistent_exit_code(files, args, code, word, capsys):
    port = transport.free_port()  # nothing listens there
    argv = [a.format(d=files, port=port) for a in args]
    if argv[0] in IN_PROCESS:  # an exception would fail the test as a traceback would
        try:
            returncode = IN_PROCESS[argv[0]](argv[1:])
        except SystemExit as e:  # argparse
            returncode = e.code
        stderr = capsys.readouterr().err
    else:
        res = _driveby(*argv)
        returncode, stderr = res.returncode, res.stderr
    err = stderr.strip()
    assert "Traceback" not in stderr, stderr
    if code == 2 and err.startswith("usage:"):  # argparse: its usage, then one line saying what is wrong
        err = err.splitlines()[-1]
    assert returncode == code and err.count("\n") == 0 and word in err, (returncode, stderr)
