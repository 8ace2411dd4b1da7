"""The CPU renderer and `gd2p show`: the picture people judge a pose by."""
from __future__ import annotations

import json

import numpy as np
import pybullet as pb
import pytest
import torch
from PIL import Image

from cli.main import main
from cli.show import show_scene
from shared.frames import transform_points
from shared.robots.hands import load_hand
from shared.world.fixed_poses import spatula_pose
from shared.world.objects import load_object
from visualisation.render import (
    CANDIDATE_COLORS,
    HAND_COLORS,
    OBJECT_RGBA,
    LegendEntry,
    RenderError,
    RenderWorld,
    candidate_items,
    hand_item,
    mesh_item,
    picture_size,
    push_markers,
    render_scene,
    render_views,
)

BOX = "proc-box-001"
HAND_RGBA = HAND_COLORS[0]


@pytest.fixture(autouse=True)
def _cache_dir(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("GD2P_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "gd2p_cache"))


@pytest.fixture(scope="module")
def box_scene(tmp_path_factory):
    """(object, T_D_O, allegro hand, spatula pose in D) for the box."""
    mp = pytest.MonkeyPatch()
    mp.setenv("GD2P_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "gd2p_cache"))
    obj = load_object(BOX)
    mp.undo()
    T_D_O = obj.T_D_O()
    hand = load_hand("allegro")
    pose = spatula_pose(hand, transform_points(T_D_O, obj.mesh.vertices))
    return obj, T_D_O, hand, pose


def chroma_mask(rgb: np.ndarray, rgba, tolerance: float = 0.06) -> np.ndarray:
    """Pixels whose chromaticity (rgb / sum) is that of `rgba`: shading scales brightness, not chromaticity."""
    rgb = rgb[..., :3].astype(np.float64)
    chroma = rgb / np.maximum(rgb.sum(-1, keepdims=True), 1.0)
    target = np.asarray(rgba[:3]) / sum(rgba[:3])
    return (np.abs(chroma - target).max(-1) < tolerance) & (rgb.sum(-1) > 60)


def read_png(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


# ------------------------------------------------------------------------------------------------- picture


def test_show_draws_the_hand_on_a_box_picture(tmp_path, box_scene):
    with_hand, without_hand = tmp_path / "spatula.png", tmp_path / "box.png"
    assert main(["show", "--object", BOX, "--hand", "allegro", "--fixed-pose", "spatula", "--out", str(with_hand)]) == 0
    assert main(["show", "--object", BOX, "--out", str(without_hand)]) == 0

    image = read_png(with_hand)
    obj, T_D_O, hand, pose = box_scene
    scene = show_scene(obj, T_D_O, hand, pose[None], ["spatula pose"])
    assert (image.shape[1], image.shape[0]) == picture_size(3, (480, 360), title=scene.title, legend=scene.legend)
    assert image.shape[1] == 3 * 480 and image.shape[0] > 360
    assert image.std(axis=(0, 1)).min() > 10  # not a uniform picture
    hand_pixels = chroma_mask(image, HAND_RGBA).sum()
    assert hand_pixels > 0.02 * 3 * 480 * 360  # the hand is big in every view
    assert chroma_mask(read_png(without_hand), HAND_RGBA).sum() < 0.05 * hand_pixels  # no orange anywhere
    assert chroma_mask(image, OBJECT_RGBA).sum() > 0.02 * 3 * 480 * 360


def test_render_scene_writes_the_announced_size(tmp_path, box_scene):
    obj, T_D_O, _, _ = box_scene
    items = [mesh_item(obj.id, obj.mesh, T_D_O)]
    legend = [LegendEntry("a", OBJECT_RGBA), LegendEntry("b", HAND_RGBA), LegendEntry("c", HAND_RGBA)]
    title = "a long title · that cannot fit · on one line of a narrow picture"
    wide = render_scene(items, tmp_path / "wide.png", views=("side", "top"), size=(200, 150), legend=legend,
                        title=title, supersample=1)
    tall = render_scene(items, tmp_path / "tall.png", views=("side", "top"), size=(200, 150), columns=1,
                        title=title, supersample=1)
    four = render_scene(items, tmp_path / "four.png", views=("iso", "side", "top", "front"), size=(100, 80), supersample=1)
    assert Image.open(wide).size == picture_size(2, (200, 150), title=title, legend=legend)
    assert Image.open(tall).size == picture_size(2, (200, 150), columns=1, title=title)
    assert Image.open(wide).size[0] == 400 and Image.open(tall).size[0] == 200
    assert Image.open(four).size == (200, 160)  # 2 x 2 tiles, no header
    # a narrower picture wraps the title onto more lines: a taller header
    narrow_header = Image.open(tall).size[1] - 2 * 150
    wide_header = picture_size(2, (200, 150), title=title)[1] - 150
    assert narrow_header > wide_header > 0


def test_every_view_frames_the_object_and_the_hand(box_scene):
    obj, T_D_O, hand, pose = box_scene
    items = [mesh_item(obj.id, obj.mesh, T_D_O), hand_item("hand", hand, pose, HAND_RGBA),
             *push_markers(np.eye(4), 0.20, 0.03)]
    for rendered in render_views(items, ("iso", "side", "top", "front"), size=(160, 120), supersample=1):
        index = rendered.item_index
        assert (index == 0).sum() > 100 and (index == 1).sum() > 100, rendered.view.name
        border = np.concatenate([index[0], index[-1], index[:, 0], index[:, -1]])
        assert np.all(border == -1), f"{rendered.view.name}: an item touches the image edge (cut off)"


def test_hand_is_drawn_at_its_kinematic_pose(box_scene):
    _, _, hand, pose = box_scene
    rng = np.random.default_rng(3)
    pose = pose.copy()
    pose[9:] = rng.uniform(hand.joint_lower.numpy(), hand.joint_upper.numpy())
    expected = hand.forward(torch.tensor(pose, dtype=torch.float32)[None]).links[0].double().numpy()
    with RenderWorld([hand_item("hand", hand, pose, HAND_RGBA)]) as world:
        body = world.body_ids[0][0]
        for j in range(pb.getNumJoints(body, physicsClientId=world.client)):
            name = pb.getJointInfo(body, j, physicsClientId=world.client)[12].decode()
            state = pb.getLinkState(body, j, computeForwardKinematics=True, physicsClientId=world.client)
            np.testing.assert_allclose(state[4], expected[hand.link_index(name), :3, 3], atol=2e-5, err_msg=name)


def test_translucent_hand_blends_over_the_scene_behind_it(box_scene):
    obj, T_D_O, hand, pose = box_scene
    obj_item = mesh_item(obj.id, obj.mesh, T_D_O)
    frame = np.array([[-0.25, -0.15, 0.0], [0.15, 0.15, 0.3]])  # one camera for the three renders

    def render(alpha: float | None):
        hands = [] if alpha is None else [hand_item("hand", hand, pose, (*HAND_RGBA[:3], alpha))]
        return render_views([obj_item, *hands], ("iso",), size=(160, 120), supersample=1, frame_points=frame)[0]

    opaque, behind, half = render(1.0), render(None), render(0.5)
    on_hand = opaque.item_index == 1
    assert on_hand.sum() > 200
    expected = 0.5 * opaque.rgb[on_hand].astype(float) + 0.5 * behind.rgb[on_hand]
    assert np.abs(half.rgb[on_hand] - expected).max() <= 1.0
    np.testing.assert_array_equal(half.rgb[~on_hand], opaque.rgb[~on_hand])


def test_contact_candidates_are_drawn_in_their_region_colours(box_scene):
    obj, T_D_O, hand, pose = box_scene
    base = [mesh_item(obj.id, obj.mesh, T_D_O), hand_item("hand", hand, pose, HAND_RGBA)]
    candidates = candidate_items("hand", hand, pose)
    assert sum(len(c.points) for c in candidates) == len(hand.contact_candidates) == 688
    plain = render_views(base, ("side",), size=(240, 180), supersample=1)[0].rgb
    marked = render_views(base + candidates, ("side",), size=(240, 180), supersample=1)[0].rgb
    tips = CANDIDATE_COLORS["tip"]
    assert chroma_mask(plain, tips).sum() == 0
    assert chroma_mask(marked, tips).sum() > 20


def test_direction_places_the_hand_behind_the_object_along_the_push(box_scene):
    obj, T_D_O, hand, pose = box_scene
    scene = show_scene(obj, T_D_O, hand, pose[None], ["spatula"], direction_deg=90.0)
    hand_base = next(item for item in scene.items if item.name == "spatula").base_transform
    np.testing.assert_allclose(hand_base[:3, 3], [-pose[1], pose[0], pose[2]], atol=1e-9)  # D's +x is world +y
    arrow = next(item for item in scene.items if item.name == "push")
    np.testing.assert_allclose(arrow.end - arrow.start, [0.0, 0.20, 0.0], atol=1e-12)


# -------------------------------------------------------------------------------------------------- errors


def _write(path, payload) -> str:
    path.write_text(payload if isinstance(payload, str) else json.dumps(payload))
    return str(path)


@pytest.mark.parametrize("case, message", [
    ("missing", "cannot read poses file"),
    ("not-json", "not valid JSON"),
    ("no-poses", '"poses" list'),
    ("width-24", "must be 25 finite numbers"),
    ("index", "--index 5 is out of range"),
])
def test_bad_poses_file_is_a_clear_error(tmp_path, capsys, box_scene, case, message):
    good = {"poses": [{"pose": box_scene[3].tolist()}]}
    files = {
        "missing": str(tmp_path / "nope.json"),
        "not-json": _write(tmp_path / "bad.json", "{poses: ["),
        "no-poses": _write(tmp_path / "empty.json", {"candidates": []}),
        "width-24": _write(tmp_path / "short.json", {"poses": [{"pose": [0.0] * 24}]}),
        "index": _write(tmp_path / "good.json", good),
    }
    args = ["show", "--object", BOX, "--hand", "allegro", "--poses", files[case], "--out", str(tmp_path / "x.png")]
    if case == "index":
        args += ["--index", "5"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("gd2p show: error:") and message in err
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("extra, message", [
    (["--hand", "shadow", "--fixed-pose", "spatula"], "unknown hand 'shadow'"),
    (["--fixed-pose", "spatula"], "need --hand"),
    (["--hand", "allegro"], "--hand needs --poses"),
    (["--size", "480by360"], "--size must be WIDTHxHEIGHT"),
    (["--views", "iso,fisheye"], "unknown view(s) ['fisheye']"),
    (["--resting-pose", "99"], "--resting-pose 99"),
    (["--hand", "allegro", "--fixed-pose", "spatula", "--index", "0"], "--index selects a pose of a --poses file"),
    (["--hand", "allegro", "--fixed-pose", "spatula", "--max-poses", "0"], "--max-poses must be >= 1"),
])
def test_bad_options_are_clear_errors(tmp_path, capsys, box_scene, extra, message):
    assert main(["show", "--object", BOX, *extra, "--out", str(tmp_path / "x.png")]) == 2
    assert message in capsys.readouterr().err


def test_max_poses_and_index_choose_the_poses_drawn(tmp_path, capsys, box_scene):
    pose = box_scene[3]
    shifted = [pose + np.r_[0.0, 0.03 * k, np.zeros(23)] for k in range(3)]
    poses = _write(tmp_path / "three.json", {"poses": [{"pose": p.tolist(), "energy": {"total": 1.0}} for p in shifted]})
    common = ["show", "--object", BOX, "--hand", "allegro", "--poses", poses, "--views", "side", "--size", "160x120"]
    assert main([*common, "--max-poses", "2", "--out", str(tmp_path / "two.png")]) == 0
    assert "(1 view, 2 poses)" in capsys.readouterr().out
    assert main([*common, "--index", "2", "--out", str(tmp_path / "one.png")]) == 0
    assert "(1 view, 1 pose)" in capsys.readouterr().out


def test_unknown_object_is_a_clear_error(tmp_path, capsys):
    assert main(["show", "--object", "no-such-object", "--out", str(tmp_path / "x.png")]) == 2
    assert "no-such-object" in capsys.readouterr().err


def test_empty_scene_is_refused():
    with pytest.raises(RenderError, match="no items"):
        render_views([], ("iso",))
