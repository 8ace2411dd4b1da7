"""Command-line input: numeric flags reject nan/inf (and out-of-range values) as usage errors naming the
flag, and values a service's request model rejects are reported by flag, not by model field."""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from cli.args import (
    FlagError,
    describe_validation_error,
    finite_float,
    float_range,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    probability,
    validate_fields,
)
from cli.main import main as gd2p

REPO = Path(__file__).resolve().parents[1]
BOX = "proc-box-003"


# ----------------------------------------------------------------------------- argparse types
@pytest.mark.parametrize("parse, text", [
    (finite_float, "nan"), (finite_float, "inf"), (finite_float, "-inf"), (finite_float, "NaN"), (finite_float, "x"),
    (positive_float, "0"), (positive_float, "-1e-9"), (positive_float, "inf"),
    (non_negative_float, "-0.5"), (non_negative_float, "nan"),
    (probability, "1.01"), (probability, "-0.1"), (probability, "nan"),
    (positive_int, "0"), (positive_int, "1.5"), (positive_int, "nan"), (non_negative_int, "-1"),
    (float_range(0.0, 1.0, low_open=True), "0"), (float_range(0.0, 1.0, high_open=True), "1"),
    (float_range(0.0, 1.0), "inf"),
])
def test_numeric_types_reject_what_a_flag_can_never_be(parse, text):
    with pytest.raises(argparse.ArgumentTypeError):
        parse(text)


def test_numeric_types_accept_their_range():
    assert finite_float("-1e300") == -1e300 and positive_float("1e-9") == 1e-9
    assert non_negative_float("0") == 0.0 and probability("0") == 0.0 and probability("1") == 1.0
    assert positive_int("3") == 3 and non_negative_int("0") == 0
    assert float_range(0.0, 1.0, low_open=True)("1") == 1.0 and float_range(-1.0, 1.0)("-1") == -1.0


# ----------------------------------------------------------------------------- nan / inf through the CLI
@pytest.mark.parametrize("argv, flag", [
    (["generate", "--object", BOX, "--hand", "allegro", "--n", "1", "--out", "x.json", "--yaw-deg", "nan"], "--yaw-deg"),
    (["sample", "--object", BOX, "--hand", "allegro", "--direction-deg", "inf"], "--direction-deg"),
    (["validate", "--object", BOX, "--hand", "allegro", "--fixed-pose", "spatula", "--distance", "nan"], "--distance"),
    (["validate", "--object", BOX, "--hand", "allegro", "--fixed-pose", "spatula", "--time-step=-inf"], "--time-step"),
    (["show", "--object", BOX, "--out", "x.png", "--direction-deg", "nan"], "--direction-deg"),
    (["train", "--dataset", "d", "--hand", "allegro", "--out", "x.pt", "--lr", "nan"], "--lr"),
    (["train", "--dataset", "d", "--hand", "allegro", "--out", "x.pt", "--fraction", "inf"], "--fraction"),
    (["replay", "x.mcap", "--rate", "inf"], "--rate"),
    (["dataset", "build", "--hand", "allegro", "--per-object", "0", "--out", "d"], "--per-object"),
])
def test_nan_and_inf_are_usage_errors_naming_the_flag(argv, flag, capsys):
    with pytest.raises(SystemExit) as exit_info:
        gd2p(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert f"error: argument {flag}: must be" in err
    assert "Traceback" not in err


def test_generate_yaw_nan_exits_2_without_a_traceback():
    done = subprocess.run([sys.executable, "-m", "cli.main", "generate", "--object", BOX, "--hand", "allegro",
                           "--n", "1", "--out", "x.json", "--yaw-deg", "nan"], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    assert "gd2p generate: error: argument --yaw-deg: must be a finite number, got 'nan'" in done.stderr
    assert "Traceback" not in done.stderr


# ----------------------------------------------------------------------------- model errors named by flag
def test_a_request_models_validation_error_is_described_by_flag():
    from shared.contracts.messages import CircleObstacle, ObjectRef, PushRequest

    with pytest.raises(ValidationError) as caught:
        PushRequest(object=ObjectRef(library_id=BOX), distance_m=2.0, options={"k": 0},
                    obstacles=[CircleObstacle(x=0, y=0, radius=0.1).model_dump() | {"radius": -1.0},
                               {"x": 0.5, "y": 0.1, "length_m": 0.0}])
    text = describe_validation_error(caught.value, {"distance_m": "--distance", "options.k": "--k", "obstacles": "--obstacle"},
                                     command="push")
    lines = text.splitlines()
    assert "gd2p push: --distance: must be <= 1.0, got 2.0" in lines
    assert "gd2p push: --k: must be >= 1, got 0" in lines
    assert "gd2p push: --obstacle (0.circle.radius): must be > 0.0, got -1.0" in lines  # each kind's own error
    assert "gd2p push: --obstacle (1.wall.length_m): must be > 0.0, got 0.0" in lines
    assert "distance_m" not in text and "'k'" not in text


def test_validate_fields_checks_only_the_given_fields_with_the_models_limits():
    from shared.contracts.messages import PhysicsSettings, SampleRequest

    assert validate_fields(SampleRequest, {"k": 1000, "seed": 0}, {"k": "--n"}) == {"k": 1000, "seed": 0}
    with pytest.raises(FlagError) as caught:
        validate_fields(SampleRequest, {"k": 1001, "sampler": "ddpx"}, {"k": "--n", "sampler": "--sampler"}, command="sample")
    lines = str(caught.value).splitlines()
    assert "gd2p sample: --n: must be <= 1000, got 1001" in lines
    assert any(line.startswith("gd2p sample: --sampler: must be 'ddpm', 'ddim' or 'nearest'") for line in lines)
    with pytest.raises(FlagError, match=r"^time_step_s: must be a finite number"):  # no flag given: the field path
        validate_fields(PhysicsSettings, {"time_step_s": float("nan")}, {})


def test_sample_reports_the_request_limit_by_flag_not_by_field(capsys):
    assert gd2p(["sample", "--object", BOX, "--hand", "allegro", "--n", "5000"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "gd2p sample: --n: must be <= 1000, got 5000"


def test_generate_reports_the_generator_job_limits_by_flag(capsys, tmp_path):
    out = tmp_path / "poses.json"
    code = gd2p(["generate", "--object", BOX, "--hand", "allegro", "--n", "1", "--iterations", "1", "--contacts", "100",
                 "--out", str(out)])
    assert code == 2
    assert capsys.readouterr().err.strip() == "gd2p generate: --contacts: must be <= 64, got 100"
    assert not out.exists()


def test_validate_reports_every_rejected_option_by_flag(capsys):
    code = gd2p(["validate", "--object", BOX, "--hand", "allegro", "--fixed-pose", "spatula", "--distance", "3",
                 "--time-step", "0.5"])
    assert code == 2
    assert capsys.readouterr().err.splitlines() == ["gd2p validate: --distance: must be <= 1.0, got 3.0",
                                                    "gd2p validate: --time-step: must be <= 0.1, got 0.5"]


def test_dataset_build_rejects_a_job_the_generator_would_refuse_before_creating_the_store(capsys, tmp_path):
    out = tmp_path / "ds"
    code = gd2p(["dataset", "build", "--hand", "allegro", "--per-object", "5000", "--object-ids", BOX,
                 "--connect", "tcp/127.0.0.1:1", "--out", str(out), "--no-progress"])
    assert code == 2
    assert capsys.readouterr().err.strip() == "gd2p dataset build: --per-object: must be <= 4096, got 5000"
    assert not out.exists()


def test_push_and_sample_refuse_a_bad_cloud_before_anything_runs(capsys, tmp_path):
    assert gd2p(["push", "--cloud", str(tmp_path / "missing.ply"), "--direction-deg", "0"]) == 2
    assert "missing.ply: no such file" in capsys.readouterr().err
    millimetres = tmp_path / "mm.npy"
    np.save(millimetres, np.random.default_rng(0).uniform(0, 500, (1000, 3)))  # a scan in millimetres
    assert gd2p(["push", "--cloud", str(millimetres), "--direction-deg", "0"]) == 2
    assert "millimetres" in capsys.readouterr().err
    good = tmp_path / "ok.npy"
    np.save(good, np.random.default_rng(0).uniform(0, 0.5, (1000, 3)))
    assert gd2p(["push", "--cloud", str(good), "--position", "0.5", "0", "--direction-deg", "0"]) == 2
    assert "the point cloud shows where the object stands" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # an object and a cloud at once
        gd2p(["push", "--cloud", str(good), "--object", "proc-box-001", "--direction-deg", "0"])
    assert gd2p(["sample", "--cloud", str(tmp_path / "missing.pcd"), "--hand", "allegro"]) == 2
    assert "missing.pcd: no such file" in capsys.readouterr().err


def test_eval_help_names_every_trial_method_and_which_are_tuning_candidates():
    """`gd2p eval --help` lists the methods by hand (importing the evaluation would slow every command by seconds);
    this keeps the list true as methods are added."""
    import re

    from cli.main import build_parser
    from evaluation.push_protocol import METHODS, TUNING_METHODS

    subparsers = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    help_text = next(a.help for a in subparsers.choices["eval"]._actions if a.dest == "methods")
    everyday, tuning = re.match(r".*\): (.*); tuning candidates \(val\): (.*); sampler-quality", help_text).groups()
    assert everyday.split(", ") == [m for m in METHODS if m not in TUNING_METHODS]
    assert set(tuning.split(", ")) == TUNING_METHODS
