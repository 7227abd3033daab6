"""``bodynet vmc``: the frame conversion alone, then the bundles on a real UDP
socket, parsed by python-osc, with every bone's world rotation rebuilt from
the local ones."""

from __future__ import annotations

import math
import socket
import threading
import time
from functools import partial
from typing import Any

import numpy as np
import pytest
import zenoh
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage
from scipy.spatial.transform import Rotation
from zenoh_helpers import Running

from bodynet.clients import live, vmc
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.skeleton import build_skeleton

SKELETON = build_skeleton()
#: Our axes in Unity's: right = -left, up = up, forward = forward.
M = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
#: Unity's humanoid hierarchy, written out here (not taken from the module).
PARENT = {"Hips": None, "Spine": "Hips", "Chest": "Spine", "Neck": "Chest", "Head": "Neck",
          "LeftUpperArm": "Chest", "LeftLowerArm": "LeftUpperArm", "LeftHand": "LeftLowerArm",
          "RightUpperArm": "Chest", "RightLowerArm": "RightUpperArm", "RightHand": "RightLowerArm",
          "LeftUpperLeg": "Hips", "LeftLowerLeg": "LeftUpperLeg", "LeftFoot": "LeftLowerLeg",
          "RightUpperLeg": "Hips", "RightLowerLeg": "RightUpperLeg",
          "RightFoot": "RightLowerLeg"}  # fmt: skip
LIMB_BONES = (("UpperArm", "upperarm"), ("LowerArm", "forearm"), ("Hand", "hand"),
              ("UpperLeg", "thigh"), ("LowerLeg", "shank"), ("Foot", "foot"))  # fmt: skip
SEGMENT = {"Hips": "pelvis", "Spine": "thorax", "Chest": "thorax", "Neck": "head", "Head": "head",
           **{f"{S}{b}": f"{s}_{g}" for S, s in (("Left", "left"), ("Right", "right"))
              for b, g in LIMB_BONES}}  # fmt: skip


#: ``/VMC/Ext/OK`` (V2.7): every argument an int, each within the values the VMC
#: protocol's specification lists (sh-akira/VirtualMotionCaptureProtocol,
#: docs/english.markdown, "Available"), written out here, not taken from the module.
OK_SPEC = (
    ("loaded", {0, 1}),  # 0 not loaded, 1 loaded
    # Uncalibrated, WaitingForCalibrating, Calibrating, Calibrated
    ("calibration state", {0, 1, 2, 3}),
    ("calibration mode", {0, 1, 2}),  # Normal, MR Normal, MR Floor fix
    ("tracking status", {0, 1}),  # Bad, OK
)


def assert_ok_within_spec(msg: OscMessage) -> None:
    """A parsed ``/VMC/Ext/OK``: four ints, each one the specification allows."""
    assert msg.address == "/VMC/Ext/OK"
    assert len(msg.params) == len(OK_SPEC), msg.params
    for value, (name, allowed) in zip(msg.params, OK_SPEC, strict=True):
        assert type(value) is int, (name, value)
        assert value in allowed, f"{name} {value} is not one of the spec's {sorted(allowed)}"


def wxyz(r: Rotation) -> tuple[float, float, float, float]:
    x, y, z, w = r.as_quat()
    return (float(w), float(x), float(y), float(z))


def random_frame(seed: int) -> pose.PoseFrame:
    rng = np.random.default_rng(seed)
    rots = Rotation.random(len(SKELETON.segments), random_state=seed)
    segments = {s: (tuple(rng.normal(size=3)), wxyz(rots[i]))
                for i, s in enumerate(SKELETON.segments)}  # fmt: skip
    return pose.PoseFrame(seed, 1_700_000_000_000_000_000 + seed, {}, {}, segments, {})


def expected_unity(frame: pose.PoseFrame, bone: str) -> Rotation:
    """The segment's orientation in Unity's frame (M R M^T), after the bone's rest
    offset: the T-pose arm (horizontal, palm down) turned onto the neutral one."""
    w, x, y, z = frame.segments[SEGMENT[bone]][1]
    r = Rotation.from_quat([x, y, z, w])
    if "Arm" in bone or "Hand" in bone:
        r = r * Rotation.from_euler("x", -90 if bone.startswith("Left") else 90, degrees=True)
    return Rotation.from_matrix(M @ r.as_matrix() @ M.T)


def unity_rotation(xyzw: list[float]) -> Rotation:
    return Rotation.from_quat(xyzw)  # Unity sends x, y, z, w; scipy's order too


def world_from_locals(bones: dict[str, list[Any]]) -> dict[str, Rotation]:
    world: dict[str, Rotation] = {}
    for bone, parent in PARENT.items():  # parents come first
        local = unity_rotation(bones[bone][4:8])
        world[bone] = local if parent is None else world[parent] * local
    return world


def worst_error_deg(frame: pose.PoseFrame, bones: dict[str, list[Any]]) -> float:
    world = world_from_locals(bones)
    return max(math.degrees((world[b] * expected_unity(frame, b).inv()).magnitude())
               for b in PARENT)  # fmt: skip


# --- conversions ---------------------------------------------------------------------------


def test_axes_and_rotations_in_unitys_frame() -> None:
    assert vmc.unity_vector((1.0, 0.0, 0.0)) == (0.0, 0.0, 1.0)  # forward
    assert vmc.unity_vector((0.0, 1.0, 0.0)) == (-1.0, 0.0, 0.0)  # left = -right
    assert vmc.unity_vector((0.0, 0.0, 1.0)) == (0.0, 1.0, 0.0)  # up
    for r in Rotation.random(50, random_state=1):
        got = vmc.unity_quat(wxyz(r))
        want = Rotation.from_matrix(M @ r.as_matrix() @ M.T)
        w, x, y, z = got
        assert (Rotation.from_quat([x, y, z, w]) * want.inv()).magnitude() < 1e-12
    # turning to the left about the vertical is a negative turn about Unity's +Y
    w, x, y, z = vmc.unity_quat(wxyz(Rotation.from_euler("z", 90, degrees=True)))
    assert np.allclose(Rotation.from_quat([x, y, z, w]).as_rotvec(), [0, -math.pi / 2, 0])


def test_the_t_pose_is_the_avatars_rest() -> None:
    tpose = dict.fromkeys(SKELETON.segments, ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)))
    for side, sign in (("left", 1), ("right", -1)):
        arm = wxyz(Rotation.from_euler("x", sign * 90, degrees=True))  # abducted, palms down
        for s in ("upperarm", "forearm", "hand"):
            tpose[f"{side}_{s}"] = ((0.0, 0.0, 0.0), arm)
    bones = vmc.bones(pose.PoseFrame(0, 0, {}, {}, tpose, {}))
    assert sorted(b.name for b in bones) == sorted(PARENT)
    for b in bones:
        assert np.allclose(b.rotation, (1.0, 0.0, 0.0, 0.0), atol=1e-12), b


def test_bundle_is_one_osc_bundle_python_osc_reads() -> None:
    f = random_frame(3)
    data = vmc.bundle(vmc.messages(f, fresh=True, t_s=1.5))
    assert OscBundle.dgram_is_bundle(data)
    msgs = [m for m in OscBundle(data) if isinstance(m, OscMessage)]
    assert [m.address for m in msgs[:3]] == ["/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Root/Pos"]
    assert_ok_within_spec(msgs[0])
    assert msgs[0].params == [1, 3, 0, 1]  # loaded, calibrated, normal mode, tracking
    assert msgs[1].params == [1.5]
    assert msgs[2].params[0] == "root"
    bones = {m.params[0]: m.params for m in msgs if m.address == "/VMC/Ext/Bone/Pos"}
    assert set(bones) == set(PARENT)
    assert worst_error_deg(f, bones) < 0.01
    stale = pose.PoseFrame(0, 0, {}, {}, f.segments, {}, {"x_deg": "uncalibrated"}, {}, ["k"])
    assert vmc.ok_args(stale, fresh=True) == (1, 0, 0, 0)
    assert vmc.ok_args(None, fresh=False) == (0, 0, 0, 0)


# --- live: a receiver on a real UDP socket ---------------------------------------------------


@pytest.fixture
def receiver() -> Any:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(10)
    yield sock
    sock.close()


def next_bundle_with_bones(sock: socket.socket, timeout: float = 20.0) -> dict[str, list[Any]]:
    deadline = time.monotonic() + timeout
    while True:
        assert time.monotonic() < deadline, "no bundle with bones"
        data, _ = sock.recvfrom(65536)
        assert OscBundle.dgram_is_bundle(data)  # one bundle per frame, nothing else
        msgs = [m for m in OscBundle(data) if isinstance(m, OscMessage)]
        assert [m.address for m in msgs[:2]] == ["/VMC/Ext/OK", "/VMC/Ext/T"]
        assert_ok_within_spec(msgs[0])
        bones = {m.params[0]: m.params for m in msgs if m.address == "/VMC/Ext/Bone/Pos"}
        if bones:
            assert msgs[0].params[0] == 1  # loaded
            return bones


def received_ok(sock: socket.socket) -> OscMessage:
    """The ``/VMC/Ext/OK`` of the next datagram on ``sock``, parsed by python-osc."""
    data, _ = sock.recvfrom(65536)
    assert OscBundle.dgram_is_bundle(data)
    msgs = [m for m in OscBundle(data) if isinstance(m, OscMessage)]
    assert msgs[0].address == "/VMC/Ext/OK"
    return msgs[0]


def test_every_ok_state_on_the_wire_is_one_the_spec_allows(receiver: socket.socket) -> None:
    """Each state of the output (nothing yet, calibrated, a dof uncalibrated, a stale
    source, no pose for a while), as the real UDP datagrams carry it."""
    output = vmc.VmcOutput("127.0.0.1", receiver.getsockname()[1], rate_hz=50)
    f = random_frame(4)
    uncalibrated = pose.PoseFrame(1, 1, {}, {}, f.segments, {}, {"x_deg": "uncalibrated"})
    stale_source = pose.PoseFrame(2, 2, {}, {}, f.segments, {}, {}, {}, ["body/x/raw"])
    try:
        got: list[OscMessage] = []
        for frame in (None, f, uncalibrated, stale_source):
            if frame is not None:
                output.on_pose("s", frame)
            output.tick(time.monotonic())
            got.append(received_ok(receiver))
        output.tick(time.monotonic() + 10 * vmc.STALE_S)  # long after the last pose
        got.append(received_ok(receiver))
    finally:
        output.close()
    for msg in got:
        assert_ok_within_spec(msg)
    # loaded, calibration state, calibration mode (always Normal), tracking status
    want = [[0, 0, 0, 0], [1, 3, 0, 1], [1, 0, 0, 1], [1, 3, 0, 0], [1, 3, 0, 0]]
    assert [m.params for m in got] == want


def test_a_bone_resting_on_an_unmeasured_angle_holds_its_last_measured_rotation(
    receiver: socket.socket,
) -> None:
    """VMC has no per-bone mark: the forearm whose elbow the pose does not
    measure keeps the rotation it had when it was measured (its child, the
    hand, measured, follows the new pose); the output counts what it held."""
    output = vmc.VmcOutput("127.0.0.1", receiver.getsockname()[1], rate_hz=50)
    first, second = random_frame(5), random_frame(6)
    flags = {"left_elbow_flexion_deg": pose.UNOBSERVED, "right_knee_flexion_deg": pose.CLAMPED}
    unmeasured = pose.PoseFrame(7, 7, {}, {}, second.segments, {}, flags)
    try:
        got = []
        for frame in (first, unmeasured, unmeasured):
            output.on_pose("s", frame)
            output.tick(time.monotonic())
            got.append(next_bundle_with_bones(receiver))
    finally:
        output.close()

    def local(frame: pose.PoseFrame, bone: str) -> Rotation:
        b = next(b for b in vmc.bones(frame) if b.name == bone)
        w, x, y, z = b.rotation
        return Rotation.from_quat([x, y, z, w])

    def angle_deg(a: Rotation, b: Rotation) -> float:
        return math.degrees((a * b.inv()).magnitude())

    for bones in got[1:]:
        sent = unity_rotation(bones["LeftLowerArm"][4:8])
        assert angle_deg(sent, local(first, "LeftLowerArm")) < 0.01
        assert angle_deg(local(first, "LeftLowerArm"), local(second, "LeftLowerArm")) > 1.0
        for bone in ("LeftHand", "RightLowerLeg", "LeftUpperArm", "Hips"):  # measured
            assert angle_deg(unity_rotation(bones[bone][4:8]), local(second, bone)) < 0.01, bone
    assert output.held.held == 2  # the forearm, in each of the two bundles


def test_vmc_receiver_rebuilds_every_segment_orientation(
    zsession: zenoh.Session, router_endpoint: str, receiver: socket.socket
) -> None:
    from zenoh_helpers import client

    out_session = client(router_endpoint)
    port = receiver.getsockname()[1]
    output = vmc.VmcOutput("127.0.0.1", port, rate_hz=50)
    running = Running(partial(live.run, out_session, output))
    try:
        first, second = random_frame(1), random_frame(2)
        matched = threading.Event()
        publisher = zsession.declare_publisher(keys.pose_key())
        deadline = time.monotonic() + 20
        while not publisher.matching_status.matching:  # the output has subscribed
            assert time.monotonic() < deadline, "the output never subscribed"
            time.sleep(0.01)
        publisher.put(pose.encode(first))
        assert worst_error_deg(first, next_bundle_with_bones(receiver)) < 0.01
        publisher.put(pose.encode(second))
        for _ in range(200):  # bundles of the first pose until the second arrives
            bones = next_bundle_with_bones(receiver)
            if worst_error_deg(first, bones) >= 0.01:
                assert worst_error_deg(second, bones) < 0.01
                matched.set()
                break
        assert matched.is_set()
    finally:
        running.stop()
        out_session.close()
    assert output.sent > 0


def test_bodynet_vmc_sends_to_the_port_it_is_given(router_endpoint: str,
                                                  receiver: socket.socket) -> None:  # fmt: skip
    from service_procs import Services, bodynet

    port = receiver.getsockname()[1]
    services = Services()
    try:
        proc = services.start("vmc", bodynet("vmc", "-e", router_endpoint, "--port", str(port),
                                             "--rate-hz", "20"))  # fmt: skip
        proc.wait_line(f"VMC bundles at 20 Hz to 127.0.0.1:{port}")
        receiver.settimeout(30)
        data, _ = receiver.recvfrom(65536)
        msgs = [m for m in OscBundle(data) if isinstance(m, OscMessage)]
        assert_ok_within_spec(msgs[0])
        assert msgs[0].params == [0, 0, 0, 0]  # nothing loaded before a pose comes
        assert proc.stop() == 0
    finally:
        services.close()


def test_a_host_that_does_not_resolve_is_told_before_any_wait() -> None:
    import subprocess

    from service_procs import bodynet

    done = subprocess.run(bodynet("vmc", "--host", "nosuch.invalid", "-e", "tcp/127.0.0.1:9"),
                          capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert done.returncode == 2
    assert "bodynet vmc: cannot resolve the receiver's host 'nosuch.invalid'" in done.stderr
    assert "Traceback" not in done.stderr
