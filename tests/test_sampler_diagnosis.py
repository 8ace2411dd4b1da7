"""The sampler diagnosis (evaluation/sampler_diagnosis.py): BPS paths, shuffled and stored sources, resumption."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import evaluation.coverage as coverage
import evaluation.sampler_diagnosis as diagnosis
from evaluation.coverage import CoverageError, DiffusionSource, PushTally, coverage_record
from evaluation.store import RECORDS_FILE
from shared.sampling.checkpoint import load_checkpoint
from shared.sampling.nearest_neighbor import NearestNeighborBaseline
from shared.sampling.sampling import PoseSampler, default_frame
from shared.world.bps import BasisPointSet
from shared.world.objects import load_object

try:  # the version-1 model is no longer shipped: restored from git history (a shallow clone has none)
    diagnosis.diagnosed_files()
except CoverageError as exc:
    pytest.skip(str(exc), allow_module_level=True)

TRAINED = "rnd-000"  # an object the diagnosed (version-1) checkpoint trained on
OTHER = "proc-cylinder-047"  # another one, of another family


@pytest.fixture(scope="module")
def checkpoint():
    return load_checkpoint(diagnosis.diagnosed_files()[0])


@pytest.fixture(scope="module")
def index():
    return NearestNeighborBaseline.load(diagnosis.diagnosed_files()[1])


def _with_basis(bps: BasisPointSet, basis: np.ndarray) -> BasisPointSet:
    return BasisPointSet.from_dict({**bps.to_dict(), "basis": basis})


def test_the_bps_comparison_agrees_on_the_shipped_paths_and_detects_a_changed_order_scale_or_sampling(checkpoint, index):
    shipped = PoseSampler(checkpoint)
    record = diagnosis.bps_paths(TRAINED, shipped, index)
    assert diagnosis.bps_agree(record) and record["train_vs_inference"] <= diagnosis.SAME_TOLERANCE
    assert diagnosis.settings_agree(diagnosis.encoding_settings(shipped, index))

    permuted = _with_basis(checkpoint.bps, checkpoint.bps.basis[np.random.default_rng(0).permutation(checkpoint.bps.n)])
    reordered = PoseSampler(dataclasses.replace(checkpoint, bps=permuted))  # the basis points in another order
    resampled = PoseSampler(dataclasses.replace(checkpoint, surface_seed=checkpoint.surface_seed + 1))
    scaled = _with_basis(checkpoint.bps, checkpoint.bps.basis * 0.9)  # training would see the object 1/0.9 larger
    for changed in (diagnosis.bps_paths(TRAINED, reordered, index), diagnosis.bps_paths(TRAINED, resampled, index),
                    diagnosis.bps_paths(TRAINED, shipped, index, training_bps=scaled)):
        assert not diagnosis.bps_agree(changed)
        assert changed["train_vs_inference"] > 1e-3
    assert not diagnosis.settings_agree(diagnosis.encoding_settings(reordered, index))
    assert not diagnosis.settings_agree(diagnosis.encoding_settings(resampled, index))


def test_shuffled_source_samples_an_object_with_its_donors_bps():
    path = str(diagnosis.diagnosed_files()[0])
    shuffled = diagnosis.ShuffledBpsSource(path, "ddim", donors=((TRAINED, OTHER),))
    obj, donor = load_object(TRAINED), load_object(OTHER)
    poses = shuffled.poses(obj, default_frame(obj), 6, 7)
    own = DiffusionSource(path, "ddim")
    np.testing.assert_array_equal(poses, own.poses(donor, default_frame(donor), 6, 7))
    assert not np.allclose(poses, own.poses(obj, default_frame(obj), 6, 7))
    with pytest.raises(CoverageError, match="no BPS donor"):
        shuffled.poses(donor, default_frame(donor), 6, 7)


def test_stored_source_returns_the_objects_own_training_poses_in_its_training_placement():
    source = diagnosis.StoredPosesSource(str(diagnosis.diagnosed_files()[1]))
    obj = load_object(TRAINED)
    with np.load(diagnosis.diagnosed_files()[1]) as data:
        row = list(data["frame_object_ids"]).index(TRAINED)
        expected = data["poses"][data["frame_index"] == row]
    assert 0 < len(expected) < 200
    np.testing.assert_array_equal(source.poses(obj, default_frame(obj), 200, 0), expected)
    assert len(source.poses(obj, default_frame(obj), 5, 0)) == 5
    with pytest.raises(CoverageError, match="default placement"):
        source.poses(obj, default_frame(obj, direction_deg=60.0), 200, 0)


def test_objects_are_the_checkpoints_own_split_and_donors_a_derangement_across_families():
    trained, held_out = diagnosis.checkpoint_objects(*diagnosis.diagnosed_files())
    assert (len(trained), len(held_out)) == (200, 22) and not set(trained) & set(held_out)
    assert TRAINED in trained and "proc-box-003" in held_out  # the first look: one of each
    picked = diagnosis.pick_objects(trained, 12)
    assert picked == diagnosis.pick_objects(list(reversed(trained)), 12) and picked[0] == TRAINED
    assert len(set(picked)) == 12 and len({diagnosis.family(o) for o in picked}) == 7
    donors = diagnosis.bps_donors(picked)
    assert sorted(donors) == sorted(donors.values()) == sorted(picked)
    assert all(a != b and diagnosis.family(a) != diagnosis.family(b) for a, b in donors.items())
    assert donors == diagnosis.bps_donors(picked) != diagnosis.bps_donors(picked, seed=1)
    with pytest.raises(CoverageError):
        diagnosis.bps_donors([TRAINED])


def test_a_resumed_run_skips_every_done_object_and_redoes_only_a_lost_one(tmp_path, monkeypatch):
    rates = {"DDPM-100": 0.5, "Stored poses": 1.0, "DDPM-100, shuffled BPS": 0.25}
    measured: list[tuple[str, str]] = []

    def scripted(source, object_id, settings):  # stands in for sampling and pushing
        measured.append((source.label(), object_id))
        successes = [i < rates[source.label()] * settings.samples for i in range(settings.samples)]
        return coverage_record(object_id, PushTally(settings.samples, successes, settings.fraction_poses), 0.0)

    encoded: list[str] = []
    real_bps_paths = diagnosis.bps_paths

    def counted_bps_paths(object_id, *args, **kwargs):
        encoded.append(object_id)
        return real_bps_paths(object_id, *args, **kwargs)

    monkeypatch.setattr(coverage, "measure_object", scripted)
    monkeypatch.setattr(diagnosis, "bps_paths", counted_bps_paths)
    report = diagnosis.run(tmp_path, quick=True, workers=1)
    units = 2 + 1 + 2 + 1 + 2  # diffusion and stored on 2 trained + 1 held out, shuffled on the 2 trained
    assert len(measured) == units and len(encoded) == 3
    summary = json.loads((report.parent / "summary.json").read_text())
    q1, q2 = summary["question_1"]["trained"], summary["question_2"]
    assert (q1["diffusion"]["pooled_validated_fraction"], q1["stored"]["pooled_validated_fraction"]) == (0.5, 1.0)
    assert q1["diffusion_minus_stored"]["value"] == pytest.approx(-0.5)
    assert q2["shuffled_minus_matched"]["value"] == pytest.approx(-0.25)
    assert summary["question_3"]["objects_agree"] == 3 and summary["question_3"]["settings_agree"]

    measured.clear()
    encoded.clear()
    again = diagnosis.run(tmp_path, quick=True, workers=1)
    assert measured == [] and encoded == []
    body = report.read_text().split("\n\n", 1)[1]
    assert again.read_text().split("\n\n", 1)[1].split("## The questions")[1] == body.split("## The questions")[1]

    records = report.parent / RECORDS_FILE
    lines = records.read_text().splitlines()
    assert len(lines) == units + 3
    lost = json.loads(lines[-1])["key"]
    records.write_text("\n".join(lines[:-1]) + "\n")  # the run was killed before its last unit was recorded
    diagnosis.run(tmp_path, quick=True, workers=1)
    prefix, object_id = lost.split("/")
    assert prefix == "shuffled" and measured == [("DDPM-100, shuffled BPS", object_id)] and encoded == []
