"""One camera, one floor, one world (humotion.capture.camera): the camera's pitch, roll and height
found from people standing on a floor, known answers from synthetic scenes."""

import math

import numpy as np
import pytest
import torch

from humotion.capture.camera import SOLES, CameraPose, estimate_camera, up_from_pitch
from humotion.capture.keypoints import body_keypoints_3d
from humotion.capture.template import template_skeleton
from humotion.skeleton import forward_kinematics


def standing_people(places, height_m=1.7):
    """(joints (22, 3), keypoints (21, 3)) of a person standing upright (arms out) at each (x, z)
    on the floor y = 0, metres, world frame (Y up)."""
    skeleton = template_skeleton(height_m)
    identity = torch.eye(3).expand(1, 22, 3, 3)
    world_r, joints = forward_kinematics(identity, torch.zeros(1, 3), skeleton.offsets, skeleton.parents)
    keypoints = body_keypoints_3d(world_r, joints, skeleton)[0]
    lift = -keypoints[SOLES, 1].min()
    return [(joints[0] + torch.tensor([x, lift, z]), keypoints + torch.tensor([x, lift, z])) for x, z in places]


def to_camera(points, pose: CameraPose):
    rotation, translation = pose.world_from_camera()
    return (points - translation) @ rotation          # inverse of world = rotation @ camera + translation


@pytest.mark.parametrize("pitch, roll, height", [(15.0, 0.0, 2.2), (-5.0, 3.0, 0.8), (35.0, -2.0, 3.0)])
def test_the_floor_of_people_at_several_places_gives_the_camera_pitch_roll_and_height(pitch, roll, height):
    truth = CameraPose(up_from_pitch(pitch, roll), height, "given")
    assert truth.pitch_deg == pytest.approx(pitch, abs=1e-4) and truth.roll_deg == pytest.approx(roll, abs=1e-4)
    people = standing_people([(-2.0, -4.0), (1.5, -6.0), (0.0, -3.0), (2.5, -8.0), (-1.0, -7.0)])
    joints = [to_camera(j, truth)[None] for j, _ in people]
    keypoints = [to_camera(k, truth)[None] for _, k in people]
    soles = [k[:, SOLES] for k in keypoints]
    found = estimate_camera(joints, keypoints, fps=30.0)
    assert found.source == "floor"
    assert found.pitch_deg == pytest.approx(pitch, abs=0.5) and found.roll_deg == pytest.approx(roll, abs=0.5)
    assert found.height == pytest.approx(height, abs=0.02)
    # the world frame puts everyone back where they stood: feet on y = 0
    assert float(found.to_world(torch.cat(soles)).reshape(-1, 3)[:, 1].abs().max()) < 0.02


def test_one_person_standing_still_gives_up_from_their_axis_and_given_values_win():
    truth = CameraPose(up_from_pitch(12.0), 1.4, "given")
    joints, keypoints = standing_people([(0.3, -3.0)])[0]
    found = estimate_camera([to_camera(joints, truth)[None]], [to_camera(keypoints, truth)[None]], 30.0)
    assert found.source == "people"                      # no spread over the floor: the body's axis
    assert found.pitch_deg == pytest.approx(12.0, abs=0.5) and found.height == pytest.approx(1.4, abs=0.03)
    given = estimate_camera([to_camera(joints, truth)[None]], [to_camera(keypoints, truth)[None]], 30.0,
                            pitch_deg=20.0, camera_height=2.0)
    assert given.source == "given" and given.pitch_deg == pytest.approx(20.0) and given.height == 2.0


def test_the_stated_camera_projects_world_points_like_the_camera_frame():
    pose = CameraPose(up_from_pitch(20.0, 4.0), 1.9, "floor")
    from humotion.capture.pipeline import default_camera
    from humotion.capture.refine import intrinsics

    camera = default_camera(640, 480)
    points = torch.tensor([[0.3, 0.5, 3.0], [-1.0, 1.2, 6.0]])
    in_camera, _ = intrinsics(camera).project(points)
    in_world, _ = pose.camera_in_world(camera).project(pose.to_world(points))
    torch.testing.assert_close(in_world, in_camera, atol=1e-3, rtol=0)
    described = pose.describe()
    assert described["position_m"] == [0.0, 1.9, 0.0] and math.isclose(described["pitch_deg"], 20.0, abs_tol=0.01)


def test_people_filmed_by_a_pitched_camera_give_its_pitch_and_height_through_the_pipeline():
    """The shipped lifter on synthetic 2D keypoints projected from people standing at five places
    on a floor (a known camera 2.5 m high, 20 degrees down): the floor of their planted feet gives
    the camera back."""
    from humotion.capture.keypoints import VirtualCamera
    from humotion.capture.lifting import load_lifter
    from humotion.capture.pipeline import CaptureConfig, Segment, camera_pose, default_camera, initial_fit

    torch.set_num_threads(1)
    people = standing_people([(-2.0, -5.0), (1.5, -7.0), (0.0, -4.0), (2.5, -9.0), (-1.5, -8.0)])
    eye, pitch = torch.tensor([0.0, 2.5, 0.0]), math.radians(20.0)
    camera = VirtualCamera.looking_at(eye, eye + torch.tensor([0.0, -math.sin(pitch), -math.cos(pitch)]), 60.0, 1280, 720)
    lifter, intrinsics = load_lifter(), default_camera(1280, 720)
    segments, fits = [], []
    for person, (_, keypoints) in enumerate(people):
        pixels, _ = camera.project(keypoints[None].expand(3, -1, -1))            # three still frames
        segment = Segment(person, np.arange(3), np.arange(3) / 30, pixels, torch.ones(3, 21))
        segments.append(segment)
        fits.append(initial_fit(segment, intrinsics, lifter, 1.7))
    pose = camera_pose(fits, segments, 30.0, CaptureConfig(), [])
    assert pose.source == "floor"
    assert pose.pitch_deg == pytest.approx(20.0, abs=1.5) and abs(pose.roll_deg) < 1.5   # 20.2 and 0.1 today
    assert pose.height == pytest.approx(2.5, abs=0.15)                                    # 2.45 m today
