"""The demo's start and exit (fingerps_driver.demo.main through fingerps_ros.command_line):
a bad option or ``FINGERPS_UMASK`` ends with exit code 2 and one error line before any node
starts; a failed step (DemoError) is ``demo: <message>`` and exit code 1.

``demo.main`` runs in this process with ``demo.run`` replaced (the real demo takes minutes),
``sys.argv[0]`` set to the installed executable's name so argparse's ``prog`` is ``demo``;
one case runs ``python -m fingerps_driver.demo`` as a subprocess.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from fingerps_driver import demo
from fingerps_driver.errors import DemoError

USAGE = ("usage: demo [-h] [--out OUT] [--bags BAGS] [--bursts BURSTS] [--rate RATE]\n"
         "            [--figures FIGURES] [--json] [--model {lambert,hk}]\n")
UMASK_ERROR = ("demo: error: FINGERPS_UMASK='bad' is not an octal umask: use e.g. 077 (owner "
               "only, the default), 027 (group may read) or keep (the user's umask)\n")


@pytest.fixture
def as_demo(monkeypatch: pytest.MonkeyPatch, restore_umask: None) -> list[object]:
    """``demo.main`` as the installed ``demo`` executable, the user's umask restored after it
    and ``demo.run`` recording its arguments instead of starting the graph."""
    runs: list[object] = []
    monkeypatch.setattr(sys, "argv", ["/install/fingerps_driver/lib/fingerps_driver/demo"])
    monkeypatch.delenv("FINGERPS_UMASK", raising=False)
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")  # restored after the test
    monkeypatch.setattr(demo, "run", lambda args: runs.append(args) or 0)
    return runs


def _exit_code(argv: list[str]) -> int:
    """demo.main's exit code, whether it returns it or argparse raises SystemExit."""
    try:
        return demo.main(argv)
    except SystemExit as exc:
        return exc.code


@pytest.mark.parametrize(("argv", "error"), [
    (["--bursts", "0"], "--bursts must be at least 1"),
    (["--bursts", "-3"], "--bursts must be at least 1"),
    (["--bursts", "abc"], "argument --bursts: invalid int value: 'abc'"),
    (["--frobnicate"], "unrecognized arguments: --frobnicate"),
    (["--model", "foo"], "argument --model: invalid choice: 'foo' (choose from 'lambert', 'hk')"),
])
def test_a_bad_option_is_the_usage_one_error_line_and_exit_2(as_demo, capsys, argv, error):
    assert _exit_code(argv) == 2
    captured = capsys.readouterr()
    assert captured.err == f"{USAGE}demo: error: {error}\n"
    assert captured.out == ""
    assert as_demo == []  # nothing started


@pytest.mark.parametrize("argv", [[], ["--bursts", "0"]])
def test_a_bad_umask_is_one_line_and_exit_2_before_the_options(as_demo, monkeypatch, capsys,
                                                              argv):
    monkeypatch.setenv("FINGERPS_UMASK", "bad")
    assert _exit_code(argv) == 2
    captured = capsys.readouterr()
    assert captured.err == UMASK_ERROR  # no usage: the options are not even read
    assert captured.out == ""
    assert as_demo == []


def test_help_shows_the_options_and_exits_0(as_demo, capsys):
    assert _exit_code(["--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(USAGE)
    for option in ("--out OUT", "--bags BAGS", "--bursts BURSTS", "--rate RATE",
                   "--figures FIGURES", "--json", "--model {lambert,hk}"):
        assert option in out
    assert as_demo == []


def test_good_options_reach_the_demo_with_owner_only_files(as_demo, capsys):
    assert demo.main(["--bursts", "2", "--model", "lambert"]) == 0
    (args,) = as_demo
    assert (args.bursts, args.model, args.rate, args.out) == (2, "lambert", 5.0, "out/demo")
    assert not args.json
    assert os.umask(0o022) == 0o077  # set before the job (the fixture restores the user's)
    assert capsys.readouterr().err == ""


def test_the_defaults_give_a_steady_state_and_json_is_an_option(as_demo, capsys):
    assert demo.main(["--json"]) == 0
    (args,) = as_demo
    # enough bursts after the first for a median and a p95, in a few seconds at the rig's rate
    assert args.bursts == demo.BURSTS == 20 and args.json
    assert args.bursts / args.rate <= 5.0
    assert os.umask(0o022) == 0o077  # set before the job (the fixture restores the user's)
    assert capsys.readouterr().err == ""


def test_a_failed_step_is_one_line_and_exit_1(as_demo, monkeypatch, capsys):
    def fails(args):
        raise DemoError("flat-field calibration failed: no white target")

    monkeypatch.setattr(demo, "run", fails)
    assert demo.main([]) == 1
    assert capsys.readouterr().err == "demo: flat-field calibration failed: no white target\n"


def test_the_module_entry_refuses_bursts_0():
    run = subprocess.run([sys.executable, "-m", "fingerps_driver.demo", "--bursts", "0"],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "FINGERPS_UMASK": "077"})
    assert run.returncode == 2
    assert run.stderr.startswith("usage: demo.py [-h]")
    assert run.stderr.endswith("demo.py: error: --bursts must be at least 1\n")
    assert run.stdout == ""
