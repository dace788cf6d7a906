"""nori-serve-lerobot's name checks and its translation both ways, without LeRobot."""

import numpy as np
import pytest

from nori_client import Image, Layout, Observation, decode
from nori_client.serve_lerobot import Inputs, MismatchError, chunk_message, check_cameras, plan

ROBOT = ["left_shoulder_pitch", "left_elbow", "left_gripper", "right_elbow"]


def config(state=2, action=2, images=None):
    inputs = {"observation.state": {"type": "STATE", "shape": [state]}}
    for cam, shape in (images or {"left_wrist": [3, 120, 160]}).items():
        inputs[f"observation.images.{cam}"] = {"type": "VISUAL", "shape": shape}
    return {"type": "act", "input_features": inputs, "output_features": {"action": {"type": "ACTION", "shape": [action]}}}


def info(state=("left_elbow", "left_gripper"), action=("left_elbow", "left_gripper"), fps=30):
    return {
        "fps": fps,
        "features": {
            "observation.state": {"dtype": "float32", "shape": [len(state)], "names": list(state)},
            "action": {"dtype": "float32", "shape": [len(action)], "names": list(action)},
        },
    }


def test_names_map_to_the_robots_order():
    p = plan(config(), info(state=("left_gripper", "left_elbow")), ROBOT)
    assert p.state_index == [2, 1]
    assert p.action_index == [1, 2]
    assert p.joint_mask == 0b0110
    assert p.cameras == {"observation.images.left_wrist": ("left_wrist", (120, 160))}
    assert p.fps == 30.0


def test_every_mismatch_is_named_at_once():
    with pytest.raises(MismatchError) as e:
        plan(
            config(state=3, images={"head": [1, 120, 160]}),
            info(state=("left_elbow", "left_knee"), action=("left_elbow", "tail")),
            ROBOT,
        )
    text = str(e.value)
    assert "joints ['left_knee'] are not the robot's" in text
    assert "joints ['tail'] are not the robot's" in text
    assert "observation.state: the policy's shape [3] is not the dataset's 2 names" in text
    assert "observation.images.head: shape [1, 120, 160] is not an RGB image" in text
    with pytest.raises(MismatchError, match="names no joints for 'action'"):
        bad = info()
        del bad["features"]["action"]["names"]
        plan(config(), bad, ROBOT)
    with pytest.raises(MismatchError, match="fps"):
        plan(config(), info(fps=0), ROBOT)
    with pytest.raises(MismatchError, match="no 'action' feature"):
        plan({**config(), "output_features": {}}, info(), ROBOT)


def test_features_the_robot_cannot_fill_are_listed():
    c = config()
    c["input_features"]["observation.current"] = {"type": "STATE", "shape": [2]}
    c["input_features"]["observation.joint_valid"] = {"type": "STATE", "shape": [2]}
    p = plan(c, info(), ROBOT)
    assert p.unserved == ["observation.current"]
    assert p.extras == ["observation.joint_valid"]


def jpeg(w, h):
    import io

    from PIL import Image as PilImage

    out = io.BytesIO()
    PilImage.fromarray(np.full((h, w, 3), 90, np.uint8)).save(out, format="JPEG")
    return out.getvalue()


def obs(position, images=("left_wrist",), size=(160, 120), t=1_000):
    return Observation(
        "r",
        1,
        t,
        np.array(position, np.float32),
        np.zeros(len(position), np.float32),
        {c: Image(c, 1, t, size[0], size[1], jpeg(*size)) for c in images},
    )


def test_cameras_are_checked_by_name_and_size():
    p = plan(config(), info(), ROBOT)
    check_cameras(p, obs([0, 0, 0, 0]))
    with pytest.raises(MismatchError, match=r"sends no camera 'left_wrist' \(it sends \['head'\]\)"):
        check_cameras(p, obs([0, 0, 0, 0], images=("head",)))
    with pytest.raises(MismatchError, match="is 320x240, the policy was trained on 160x120"):
        check_cameras(p, obs([0, 0, 0, 0], size=(320, 240)))


def test_a_missing_reading_is_held_and_nothing_goes_before_every_joint_was_read():
    c = config()
    c["input_features"]["observation.joint_valid"] = {"type": "STATE", "shape": [2]}
    inputs = Inputs(plan(c, info(), ROBOT), 4)
    assert inputs.take(obs([0, np.nan, 0.5, 0])) is None, "the elbow never read"
    x = inputs.take(obs([0, -0.5, 0.5, 0]))
    assert x["observation.state"].tolist() == [-0.5, 0.5]
    x = inputs.take(obs([0, np.nan, 0.25, 0]))
    assert x["observation.state"].tolist() == [-0.5, 0.25], "the elbow held at its last reading"
    assert x["observation.joint_valid"].tolist() == [0.0, 1.0]
    assert x["observation.images.left_wrist"].shape == (120, 160, 3)
    assert inputs.take(obs([0, 0, 0, 0], images=())) is None, "no picture, no inference"


def test_the_chunk_goes_to_the_policys_joints_on_the_robots_clock():
    p = plan(config(), info(state=("left_gripper", "left_elbow"), action=("left_gripper", "left_elbow")), ROBOT)
    layout = Layout(ROBOT, np.full(4, -3, np.float32), np.full(4, 3, np.float32))
    chunk = np.array([[0.1, -0.2], [0.3, -0.4], [0.5, -0.6]], np.float32)
    m = decode("ActionChunk", chunk_message(p, layout, obs([0, 0, 0, 0], t=5_000_000), chunk, seq=9, steps=2))
    assert (m["seq"], m["observation_ns"], m["joint_count"], m["joint_mask"]) == (9, 5_000_000, 4, 0b0110)
    assert m["step_offsets_ns"] == [0, 33_333_333]
    targets = m["targets"].reshape(2, 4)
    assert targets[:, 2].tolist() == pytest.approx([0.1, 0.3]) and targets[:, 1].tolist() == pytest.approx([-0.2, -0.4])
    assert targets[:, [0, 3]].tolist() == [[0, 0], [0, 0]]
    with pytest.raises(MismatchError, match="chunk of shape"):
        chunk_message(p, layout, obs([0, 0, 0, 0]), np.zeros((3, 5), np.float32), 1, None)


def body_obs(position, lift=0.4, t=1):
    o = obs(position, t=t)
    o.lift = None if lift is None else {"height_m": lift, "goal_m": 0.5, "state": 2, "held": 0, "duty_wait_s": 0.0}
    o.base = {"x_m": 0.0, "y_m": 0.0, "heading_rad": 0.0, "linear_m_s": 0.1, "angular_rad_s": -0.25,
              "field_distance_m": -1.0, "flags": 0}
    return o


def test_the_lift_and_base_after_the_joints_are_observed_and_commanded():
    body = ("lift.height_m", "base.linear_m_s", "base.angular_rad_s")
    names = ("left_elbow", "left_gripper") + body
    p = plan(config(state=5, action=5), info(state=names, action=names), ROBOT)
    assert (p.state_index, p.state_body, p.action_index, p.action_body) == ([1, 2], [0, 1, 2], [1, 2], [0, 1, 2])
    inputs = Inputs(p, 4)
    assert inputs.take(body_obs([0, -0.5, 0.5, 0], lift=None)) is None, "the lift not homed: nothing to act on"
    assert inputs.take(body_obs([0, -0.5, 0.5, 0], lift=np.nan)) is None
    x = inputs.take(body_obs([0, -0.5, 0.5, 0]))
    assert x["observation.state"].tolist() == pytest.approx([-0.5, 0.5, 0.4, 0.1, -0.25])
    layout = Layout(ROBOT, np.full(4, -3, np.float32), np.full(4, 3, np.float32))
    chunk = np.array([[0.1, 0.2, 0.3, 0.05, 0.5], [0.1, 0.2, 0.35, 0.1, 0.25]], np.float32)
    m = decode("ActionChunk", chunk_message(p, layout, body_obs([0, 0, 0, 0]), chunk, seq=1, steps=None))
    assert m["joint_mask"] == 0b0110
    assert list(m["lift_m"]) == pytest.approx([0.3, 0.35])
    assert list(m["base_twist"]) == pytest.approx([0.05, 0.5, 0.1, 0.25])
    # The base alone commanded (the state still sees everything): no joint in the mask.
    only_base = plan(config(state=5, action=2), info(state=names, action=body[1:]), ROBOT)
    m = decode("ActionChunk", chunk_message(only_base, layout, body_obs([0, 0, 0, 0]), chunk[:, 3:], 2, None))
    assert (m["joint_mask"], list(m["lift_m"])) == (0, [])
    # The body before a joint, or half the base: named.
    with pytest.raises(MismatchError, match="after the joints"):
        plan(config(state=3), info(state=("lift.height_m", "left_elbow", "left_gripper")), ROBOT)
    with pytest.raises(MismatchError, match="speed and turn rate together"):
        plan(config(action=3), info(action=("left_elbow", "left_gripper", "base.linear_m_s")), ROBOT)
