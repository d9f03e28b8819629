"""``python -m ti_dk.tradeoff`` as a user runs it: a tiny pilot end to end, and bad input refused in one line."""
from .helpers import command


def test_command_runs_a_tiny_pilot_and_writes_the_pick(tmp_path):
    r = command("ti_dk.tradeoff", "void1d", "--set", "cells=[16]", "--set", "ppc=12", "--t-end", "0.004",
                "--set", "output_times=[0.004]", "--no-defaults", "--try", "method=fv", "--pilot-ensemble", "8",
                "--below", "20", "--ensemble", "50", "--accuracy", "1e9", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert "the pilot: 2 settings of 8 members" in r.stderr
    assert "bias against the particle method, in SEs of a run of 50 members" in r.stdout
    assert "pick:" in r.stdout and "void1d_pick.toml" in r.stdout
    assert (tmp_path / "void1d_pick.toml").read_text().startswith("# ti_dk.tradeoff's pick for void1d")
    assert {p.name for p in tmp_path.iterdir()} == {"tradeoff.csv", "tradeoff.h5", "tradeoff.png", "void1d_pick.toml"}


def test_bad_input_is_one_line_and_exit_2(tmp_path):
    for args, says in ((["--accuracy", "2", "--rel-error", "0.1"], "not allowed with argument"),
                       (["--try", "nonsense=1", "--no-defaults"], "nonsense"),
                       (["--set", "C"], "KEY=VALUE")):
        r = command("ti_dk.tradeoff", "void1d", *args, "--out", str(tmp_path / "x"))
        assert r.returncode == 2 and says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert "python -m ti_dk.tradeoff --help" in r.stderr or "argument" not in r.stderr
    assert not (tmp_path / "x").exists()
