"""Issue 23: a body that looks right in every pose. The shoulders of a body with its arms hanging
(no peaks from clavicles shrugged by the mocap's collars) and its feet on the floor through a
whole real walk (not only on the first frame)."""

import numpy as np
import pytest
import torch

from humotion.body import quality
from humotion.body.export import feet_on_floor, pose_motion, rest_body
from humotion.body.floor import floor_offsets, lowest_foot_points
from humotion.body.model import load_body_model
from humotion.body.posing import canonical_to_rig
from humotion.io import load_motion

WALK = ("cmu_mocgui_s02/02_01.amc", "cmu_mocgui_s02/02.asf")


@pytest.fixture(scope="module")
def low():
    torch.set_num_threads(1)
    return load_body_model("low")


@pytest.fixture(scope="module")
def tall(low):
    return rest_body(low, low.shape_from_measurements(1.85, 80.0))


def shoulder_stretch(model, body, canonical, **kwargs) -> float:
    """Worst edge stretch at the tops of the shoulders of the body in canonical poses (P, 22, 4)."""
    local = canonical_to_rig(canonical.double(), body.vertices.double(), body.joints.double(), model.joint_names,
                             model.parents, **kwargs)
    with torch.no_grad():
        posed = model(rest_vertices=body.vertices[None], pose=local.float()).vertices
    rest = body.vertices.double().numpy()
    edges = quality.mesh_edges(model.faces.numpy())
    masks = quality.region_masks(rest, body.joints.numpy(), model.joint_names)
    return quality.region_stretch(quality.edge_stretch(posed.double().numpy(), rest, edges), edges,
                                  masks["shoulders"])["worst"]


def test_hanging_arms_leave_the_shoulders_smooth(mocap, low, tall):
    arms_down = quality.pose_set(mocap, quality.POSE_SET[:1])["arms_down"][None]
    assert shoulder_stretch(low, tall, arms_down) < 1.6
    # the collars aimed as the mapping did before: the peaks (edges on top of the shoulders 2.5x longer)
    assert shoulder_stretch(low, tall, arms_down, held=()) > 2.0


def test_regions_are_balls_around_their_joints(low, tall):
    masks = quality.region_masks(tall.vertices.numpy(), tall.joints.numpy(), low.joint_names)
    assert set(masks) == set(quality.REGION_JOINTS)
    assert not (masks["shoulders"] & masks["armpits"]).any()
    y = tall.vertices[:, 1].numpy()
    assert y[masks["shoulders"]].min() > y[masks["armpits"]].min()
    for region, mask in masks.items():
        assert 10 < mask.sum() < 0.2 * len(mask), region
    # an edge at its rest length is not stretched; doubled or halved, a factor 2
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    posed = np.array([[[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.5, 0.0]]])
    np.testing.assert_allclose(quality.edge_stretch(posed, rest, np.array([[0, 1], [0, 2], [1, 2]]))[0, :2], [2.0, 2.0])


def test_feet_stay_on_the_floor_through_a_real_walk(mocap, low, tall):
    motion = load_motion(mocap / WALK[0], asf=mocap / WALK[1]).resample(30.0)
    rotations, root = pose_motion(tall, motion)
    points = lowest_foot_points(low, tall.vertices, tall.joints, rotations, root - tall.joints[0]).numpy()
    _, contacts = feet_on_floor(tall, rotations, root, motion.fps)
    assert contacts.any(1).mean() > 0.8                        # a walk: nearly always a foot down
    heights = points[:, :, 0, 1]
    assert np.abs(heights[contacts]).max() < 0.02              # feet in contact: on the floor
    assert heights.min() > -0.02                               # no foot through it
    # placed from the first frame's ankles only, the walk drifted off the floor
    _, before = pose_motion(tall, motion, floor=False)
    drift = lowest_foot_points(low, tall.vertices, tall.joints, rotations, before - tall.joints[0]).numpy()
    assert np.abs(drift[:, :, 0, 1][contacts]).max() > 0.03


def test_a_foot_in_the_air_stays_in_the_air():
    """A jump: both feet leave the floor for half a second; the offsets between the contacts are
    interpolated, so the flight is kept, and the standing parts land on y = 0."""
    fps, count = 30.0, 60
    t = np.arange(count) / fps
    flight = (t > 0.8) & (t < 1.3)
    height = np.where(flight, 1.2 * (t - 0.8) * (1.3 - t) * 4, 0.0) + 0.07    # standing 7 cm too high
    points = np.zeros((count, 2, 2, 3))
    points[:, :, 0, 1] = height[:, None]
    points[:, :, 1, 1] = height[:, None] + 0.05
    points[:, 1, :, 0] = 0.2
    offsets, contacts = floor_offsets(points, fps)
    assert contacts[~flight].mean() > 0.8
    assert not contacts[flight].any()
    landed = height + offsets
    assert np.abs(landed[~flight & (np.abs(t - 1.05) > 0.4)]).max() < 0.005
    assert landed[np.abs(t - 1.05) < 0.05].min() > 0.25                        # the apex stays up


def test_a_still_or_short_motion_stands_on_the_floor():
    """A photo's one frame, or two frames standing still, land on the floor."""
    for count in (1, 2):
        points = np.zeros((count, 2, 2, 3))
        points[:, :, 0, 1] = 0.04
        offsets, contacts = floor_offsets(points, 30.0)
        assert contacts.all()
        np.testing.assert_allclose(offsets, -0.04)
