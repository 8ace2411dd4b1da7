"""Per-hand configuration: where the URDF comes from, joint order, palm geometry, contact-candidate regions.

Contact candidates follow the paper's appendix tables (Allegro Table "contact_candidates_allegro", LEAP Table
"contact_candidates_leap"). The paper samples finger/palm candidates "uniformly over the rigid body surface"
and fingertip candidates "uniformly on the hemisphere of each tip". Here every region is the part of a link's
collision surface that faces a given direction (`facing`, link frame) by more than `min_cos`, and is not
covered by another primitive of the hand at the open pose:
- finger links and palm: the contact (palmar) side, i.e. the face the finger flexes towards (min_cos 0.5
  selects that box face and excludes the sides and the back);
- tips: the distal hemisphere of the tip shape (`facing` = the finger's distal direction, min_cos 0).
Prior whole-hand samplers (DexGraspNet, get_a_grip) also keep candidates on the grasping side only; a push
uses the same side, since E_dir turns the palm towards the push.

Allegro mapping of the paper's "link No." to example-robot-data link names: tip_1..tip_4 -> link_3.0_tip,
link_7.0_tip, link_11.0_tip, link_15.0_tip (index, middle, ring, thumb); finger link N -> link_N.0;
palm_link -> palm_link.  96 x 4 + 16 x 11 + 128 = 688 candidates.

LEAP: the table lists "mcp_joint & dip" (16 each, fingers 1-3), "dip" (4 each, fingers 1-3),
"thumb_pip & thumb_dip" (16 each), tips (24 each) and the palm (128). "dip" appears twice; the second
column is read as the small `pip` link (the abduction bracket between mcp_joint and dip), the only finger
link the table would otherwise leave out. 24 x 4 + 16 x 6 + 4 x 3 + 16 x 2 + 128 = 364 candidates.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from shared.robots.hands.leap_urdf import ASSET_PATH as LEAP_URDF_PATH
from shared.robots.hands.urdf import example_robot_data_file, resolved_urdf


@dataclass(frozen=True)
class ContactRegion:
    """`count` candidates on the surface of `link` whose outward normal n satisfies n . facing > min_cos."""

    name: str
    link: str
    count: int
    facing: tuple[float, float, float]
    min_cos: float


@dataclass(frozen=True)
class HandSpec:
    name: str
    joint_names: tuple[str, ...]  # order of the 16 joint entries of the pose vector
    palm_link: str
    palm_normal_base: tuple[float, float, float]  # out of the palm's contact face, base frame
    finger_direction_base: tuple[float, float, float]  # wrist -> fingers, base frame, orthogonal to the normal
    mount_point_base: tuple[float, float, float]  # centre of the back of the palm (where an arm adapter sits)
    contact_regions: tuple[ContactRegion, ...]
    open_joints: dict[str, float] = field(default_factory=dict)  # non-zero entries of the open pose
    # Link pairs (besides parent/child) whose penetration keypoints may not be compared: they touch by design.
    self_collision_exclusions: tuple[tuple[str, str], ...] = ()

    def urdf_path(self) -> Path:
        return _URDF_SOURCES[self.name]()


def _regions(prefix: str, links: Iterable[str], count: int, facing: tuple[float, float, float],
             min_cos: float) -> tuple[ContactRegion, ...]:
    return tuple(ContactRegion(f"{prefix}:{link}", link, count, facing, min_cos) for link in links)


_FACE = 0.5  # selects one box face (|cos| of the adjacent faces is 0)
_HEMISPHERE = 1e-3  # strictly the distal half (drops cylinder caps, whose normals are orthogonal to it)

ALLEGRO = HandSpec(
    name="allegro",
    joint_names=tuple(f"joint_{i}.0" for i in range(16)),  # index 0-3, middle 4-7, ring 8-11, thumb 12-15
    palm_link="palm_link",
    # Fingers flex about +y, so their tips move towards +x: the palm's contact face is the +x face of the
    # palm box (x = +0.0111 m); the fingers point along +z.
    palm_normal_base=(1.0, 0.0, 0.0),
    finger_direction_base=(0.0, 0.0, 1.0),
    mount_point_base=(-0.0297, 0.0, -0.0475),  # centre of the palm box's back (-x) face
    contact_regions=(
        _regions("tip", ("link_3.0_tip", "link_7.0_tip", "link_11.0_tip", "link_15.0_tip"), 96, (0.0, 0.0, 1.0),
                 _HEMISPHERE)
        + _regions("finger", tuple(f"link_{i}.0" for i in (1, 2, 3, 5, 6, 7, 9, 10, 11, 14, 15)), 16,
                   (1.0, 0.0, 0.0), _FACE)
        + _regions("palm", ("palm_link",), 128, (1.0, 0.0, 0.0), _FACE)
    ),
    # The thumb's lower limit for joint 12 (rotation towards the palm) is 0.263 rad; every other joint is 0.
    open_joints={"joint_12.0": 0.263},
    # The thumb's rotation link rests against the palm at joint 12's lower stop (their boxes overlap there).
    self_collision_exclusions=(("palm_link", "link_13.0"),),
)

_LEAP_FINGERS = ("", "_2", "_3")
LEAP = HandSpec(
    name="leap",
    joint_names=tuple(str(i) for i in range(16)),  # = Dynamixel ids: index 0-3, middle 4-7, ring 8-11, thumb 12-15
    palm_link="palm_lower",
    # Finger flexion moves the tips towards -z of palm_lower; fingers point along +x.
    palm_normal_base=(0.0, 0.0, -1.0),
    finger_direction_base=(1.0, 0.0, 0.0),
    mount_point_base=(-0.049, -0.035, 0.012),  # centre of the palm's back (+z) face
    contact_regions=(
        _regions("tip", tuple("fingertip" + s for s in _LEAP_FINGERS) + ("thumb_fingertip",), 24, (0.0, -1.0, 0.0),
                 _HEMISPHERE)
        # Palmar side in each link frame (at q = 0): mcp_joint +x, dip -x, pip -z, thumb links +x (the thumb
        # flexes towards the fingers, +x of the palm, in its open pose).
        + _regions("finger", tuple("mcp_joint" + s for s in _LEAP_FINGERS), 16, (1.0, 0.0, 0.0), _FACE)
        + _regions("finger", tuple("dip" + s for s in _LEAP_FINGERS), 16, (-1.0, 0.0, 0.0), _FACE)
        + _regions("finger", tuple("pip" + s for s in _LEAP_FINGERS), 4, (0.0, 0.0, -1.0), _FACE)
        + _regions("finger", ("thumb_pip", "thumb_dip"), 16, (1.0, 0.0, 0.0), _FACE)
        + _regions("palm", ("palm_lower",), 128, (0.0, 0.0, -1.0), _FACE)
    ),
)

HAND_SPECS: dict[str, HandSpec] = {spec.name: spec for spec in (ALLEGRO, LEAP)}

_URDF_SOURCES = {
    "allegro": lambda: resolved_urdf(
        example_robot_data_file("allegro_hand_description/urdf/allegro_right_hand.urdf"), "allegro_right"),
    "leap": lambda: LEAP_URDF_PATH,
}
