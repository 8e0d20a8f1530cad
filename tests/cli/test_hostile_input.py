"""Randomised hostile input, with hypothesis: whatever is thrown at the command line or
the Python API, bad input is exit 2 (InputError) with one line naming the problem, no traceback,
no output directory created, an existing output directory untouched.

Each strategy draws values that are bad by construction (the oracle below says why), so every
example must be rejected before anything is computed.
"""
import math
import string

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from fem_dual import RunConfig
from fem_dual.cli import main
from fem_dual.config import MAX_DEGREE, MAX_VERTICES
from fem_dual.errors import InputError

pytestmark = pytest.mark.serial
SETTINGS = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])

HOSTILE_TEXT = st.sampled_from(["nan", "NaN", "-nan", "inf", "-inf", "Infinity", "1e400",
                                "-1e400", "abc", "", " ", "1,2", "--", "0x10", "1e", "e5", ".",
                                "None", "[]", "1 2", "\u00a0", "1;2", "=", "1=2"])
RANDOM_TEXT = st.text(alphabet=string.printable + "\u00e9\u0661\u2212", max_size=12)


def _number(text):
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _bad_whole(low, high):
    def bad(text):
        value = _number(text)
        return value is None or value != int(value) or not low <= value <= high
    return bad


ORACLES = {  # option -> (is this text bad?)
    "--T": lambda text: not ((_number(text) or 0) > 0),
    "--cells": _bad_whole(1, MAX_VERTICES),
    "--slabs": _bad_whole(1, MAX_VERTICES),
    "--degree": _bad_whole(1, MAX_DEGREE),
    "--max-halvings": _bad_whole(0, 30),
    "--superpose": lambda text: text not in ("auto", "yes", "no"),
    "--staging": lambda text: text not in ("auto", "off"),
    "--recovery": lambda text: text not in ("momentum", "dtp"),
}
HUGE = st.integers(min_value=MAX_VERTICES + 1, max_value=10**30).map(str)
NEGATIVE = st.integers(max_value=0).map(str)
VALUES = HOSTILE_TEXT | RANDOM_TEXT | HUGE | NEGATIVE | st.floats().map(repr)


def _bad_vector(text, n=2):
    items = text.split(",")
    return len(items) != n or any(_number(item) is None for item in items)


def _check_rejected(argv, tmp_path, capsys):
    """argv is bad input: exit 2, one line, no traceback, output untouched."""
    existing = tmp_path / "existing"
    existing.mkdir(exist_ok=True)
    (existing / "ziegler.xdmf").write_text("earlier result")
    fresh = tmp_path / "fresh"
    for out in (existing, fresh):
        capsys.readouterr()
        assert main(argv + ["--out", str(out)]) == 2, argv
        captured = capsys.readouterr()
        assert captured.out == ""
        err = captured.err
        assert err.startswith("fem-dual: error: ") and err.count("\n") == 1, (argv, err)
        assert "Traceback" not in err
    assert not fresh.exists()
    assert sorted(p.name for p in existing.iterdir()) == ["ziegler.xdmf"]
    assert (existing / "ziegler.xdmf").read_text() == "earlier result"
    return err


@SETTINGS
@given(option=st.sampled_from(sorted(ORACLES)), value=VALUES)
def test_hostile_option_values(option, value, tmp_path, capsys):
    assume(ORACLES[option](value))
    err = _check_rejected(["run", "ziegler", "--cells", "4", f"{option}={value}"], tmp_path,
                          capsys)
    assert option.lstrip("-") in err or "too large" in err


@SETTINGS
@given(option=st.sampled_from(["--x0", "--v0"]), value=VALUES | st.lists(
    st.floats(allow_nan=True, allow_infinity=True), max_size=4).map(
        lambda xs: ",".join(map(repr, xs))))
def test_hostile_initial_states(option, value, tmp_path, capsys):
    assume(_bad_vector(value))
    err = _check_rejected(["run", "ziegler", f"{option}={value}"], tmp_path, capsys)
    assert option.lstrip("-") in err


@SETTINGS
@given(name=st.sampled_from(["P", "m1", "c2", "l", "A", "weights", "nope", "", " "]),
       value=VALUES, sep=st.sampled_from(["=", "", "=="]))
def test_hostile_scene_parameters(name, value, sep, tmp_path, capsys):
    if name == "weights":
        assume(value not in ("auto", "identity", "energy"))
    elif name in ("m1", "l"):
        assume(not ((_number(value) or 0) > 0))
    elif name in ("P", "c2"):
        assume(_number(value) is None)
    elif name == "A":
        assume(_number(value) is None or _number(value) <= 0)
    err = _check_rejected(["run", "ziegler", "--param", f"{name}{sep}{value}"], tmp_path,
                          capsys)
    assert "param" in err or name.strip() in err


def _bad_list(low, high):
    bad_item = _bad_whole(low, high)
    return lambda text: any(bad_item(item) for item in text.split(","))


BENCH_ORACLES = {"--cells": _bad_list(1, MAX_VERTICES), "--degrees": _bad_list(1, MAX_DEGREE),
                 "--slabs": _bad_list(1, MAX_VERTICES), "--repeats": _bad_list(1, 100)}


@SETTINGS
@given(option=st.sampled_from(sorted(BENCH_ORACLES)), value=VALUES | st.lists(
    VALUES, min_size=1, max_size=3).map(",".join))
def test_hostile_bench_lists(option, value, tmp_path, capsys):
    assume(BENCH_ORACLES[option](value))
    err = _check_rejected(["bench", "ziegler", f"{option}={value}"], tmp_path, capsys)
    assert option.lstrip("-").rstrip("s") in err or "too large" in err


@SETTINGS
@given(scene=st.sampled_from(["ziegler", "curl3d", "nope", "", "ZIEGLER", "../x"]),
       command=st.sampled_from(["run", "bench", "flutter"]))
def test_unknown_scenes(scene, command, tmp_path, capsys):
    assume(scene not in ("ziegler", "curl3d"))
    _check_rejected([command, scene], tmp_path, capsys)


ANY = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20),
                st.floats(allow_nan=True, allow_infinity=True), RANDOM_TEXT, HOSTILE_TEXT,
                st.lists(st.floats(allow_nan=True), max_size=3))


@settings(max_examples=150, deadline=None, derandomize=True, database=None)
@given(key=st.sampled_from(["T", "cells", "degree", "slabs", "x0", "v0", "max_halvings",
                            "superpose", "staging", "recovery"]), value=ANY)
def test_python_api_raises_input_error_or_accepts(key, value):
    """RunConfig.create either accepts a value (and then it is a sane one) or raises InputError:
    never another exception."""
    try:
        config = RunConfig.create("ziegler", **{key: value})
    except InputError as exc:
        assert "\n" not in str(exc) and str(exc)
        return
    assert math.isfinite(config.T) and config.T > 0
    assert 1 <= config.cells and 1 <= config.degree <= MAX_DEGREE and 1 <= config.slabs
    assert config.cells * config.slabs <= MAX_VERTICES
    assert all(math.isfinite(v) for v in [*config.x0, *config.v0])


@SETTINGS
@given(tail=st.lists(st.text(alphabet=string.ascii_letters + "._-", min_size=1, max_size=8),
                     min_size=1, max_size=3), command=st.sampled_from(["run", "bench"]))
def test_unwritable_out_anywhere_below_a_file(tail, command, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("keep me")
    out = blocker.joinpath(*tail)
    capsys.readouterr()
    assert main([command, "ziegler", "--cells", "4", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fem-dual: error: --out") and err.count("\n") == 1, err
    assert blocker.read_text() == "keep me"
