"""DetAug math without a simulator: arcs, labels, timing, segmentation and plan assembly."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from detaug_gym.augment.arcs import (
    arc_frame,
    arc_label,
    arc_length,
    arc_points,
    arc_steps,
    bulge_direction,
    label_to_arc,
    min_jerk,
    smooth_trapezoid,
)
from detaug_gym.augment.detaug import MODE as DETAUG
from detaug_gym.augment.detaug import make_label
from detaug_gym.augment.plan import ArcSample, Timing, build_plan
from detaug_gym.augment.segment import SegmentConfig, Transit, closed_runs, segment_gripper
from detaug_gym.rotations import slerp

coord = st.floats(-1.0, 1.0, allow_nan=False)
point = st.tuples(coord, coord, coord).map(np.array)
phis = st.floats(0.15 * np.pi, 0.85 * np.pi)
thetas = st.floats(0.0, np.pi)


def _distinct(p0, p1):
    return np.linalg.norm(p1 - p0) > 1e-3


@settings(max_examples=150, deadline=None)
@given(point, point, phis, thetas)
def test_arc_endpoints_are_the_chord_endpoints(p0, p1, phi, theta):
    if not _distinct(p0, p1):
        return
    pts = arc_points(p0, p1, phi, theta, np.linspace(0.0, 1.0, 33))
    np.testing.assert_array_equal(pts[0], p0)
    np.testing.assert_array_equal(pts[-1], p1)
    # a circular arc: all points equidistant from the centre, and the polyline length matches the formula
    dense = arc_points(p0, p1, phi, theta, np.linspace(0.0, 1.0, 4001))
    length = np.linalg.norm(np.diff(dense, axis=0), axis=1).sum()
    assert length == pytest.approx(arc_length(np.linalg.norm(p1 - p0), phi), rel=1e-4)


@settings(max_examples=100, deadline=None)
@given(point, point, thetas, st.floats(1e-7, 1e-3))
def test_small_phi_gives_the_straight_chord(p0, p1, theta, phi):
    if not _distinct(p0, p1):
        return
    s = np.linspace(0.0, 1.0, 17)
    chord = p0 + s[:, None] * (p1 - p0)
    bent = arc_points(p0, p1, phi, theta, s)
    # the sagitta is chord/2 * tan(phi/2): first order in phi
    assert np.abs(bent - chord).max() <= np.linalg.norm(p1 - p0) * phi
    np.testing.assert_allclose(arc_points(p0, p1, 0.0, theta, s), chord, atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(point, point, thetas)
def test_bulge_is_perpendicular_and_never_down(p0, p1, theta):
    if not _distinct(p0, p1):
        return
    d, e_side, e_up = arc_frame(p0, p1)
    b = bulge_direction(p0, p1, theta)
    assert abs(b @ d) < 1e-9 and np.linalg.norm(b) == pytest.approx(1.0)
    # theta in [0, pi] sweeps side, top, other side (a vertical chord has only horizontal bulges)
    assert e_up[2] >= -1e-12 and b[2] >= -1e-6


@given(st.floats(0.0, 3.0), thetas)
def test_label_is_zero_iff_unbent_and_inverts(phi, theta):
    label = arc_label(phi, theta)
    assert (np.abs(label).max() == 0.0) == (phi == 0.0)
    if phi > 1e-9:
        back_phi, back_theta = label_to_arc(label)
        assert back_phi == pytest.approx(phi) and back_theta == pytest.approx(theta, abs=1e-9)


def test_timing_profiles_start_and_end_at_rest():
    u = np.linspace(0.0, 1.0, 201)
    for f in (min_jerk, smooth_trapezoid):
        s = f(u)
        assert s[0] == 0.0 and s[-1] == pytest.approx(1.0) and np.all(np.diff(s) >= 0)
        v = np.diff(s)
        assert v[0] < 0.05 * v.max() and v[-1] < 0.05 * v.max()
    assert np.diff(smooth_trapezoid(u, 0.3)).max() * 200 == pytest.approx(1 / 0.7, rel=0.02)


def test_arc_steps_keep_mean_speed_and_respect_the_speed_cap():
    assert arc_steps(20, 0.2, 0.4) == 40  # twice as long, same mean speed
    assert arc_steps(20, 0.2, 0.4, max_speed=0.01, peak=1.5) == 60  # the controller cap wins


def test_slerp_endpoints_and_unit_norm():
    rng = np.random.default_rng(0)
    q0, q1 = rng.normal(size=4), rng.normal(size=4)
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    out = slerp(q0, q1, np.linspace(0, 1, 11))
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0)
    np.testing.assert_allclose(out[0], q0, atol=1e-12)
    assert abs(abs(out[-1] @ q1) - 1.0) < 1e-12


# ---------------------------------------------------------------------------------------------- segmentation
def _command(*runs):
    """Gripper command from (value, length) runs."""
    return np.concatenate([np.full(n, v, dtype=np.float32) for v, n in runs])


def test_segmentation_one_grasp_held_to_the_end():
    cmd = _command((-1, 40), (1, 50))
    seg = segment_gripper(cmd, SegmentConfig(margin_s=0.4, window_s=0.25))
    assert len(seg.grasps) == 1 and seg.grasps[0].close == 40 and seg.grasps[0].release is None
    approach, carry = seg.transits
    assert (approach.kind, approach.start, approach.end) == ("approach", 0, 40 - 5 - 8)
    assert (carry.kind, carry.start, carry.end) == ("carry", 40 + 5 + 8, 89 - 5 - 8)


def test_segmentation_two_grasps_and_ignores_blips():
    cmd = _command((-1, 40), (1, 3), (-1, 10), (1, 40), (-1, 40), (1, 40), (-1, 30))
    assert closed_runs(cmd, 5) == [(53, 92), (133, 172)]
    seg = segment_gripper(cmd)
    assert [g.close for g in seg.grasps] == [53, 133] and [g.release for g in seg.grasps] == [93, 173]
    kinds = [(t.kind, t.grasp) for t in seg.transits]
    assert kinds == [("approach", 0), ("carry", 0), ("approach", 1), ("carry", 1)]
    assert seg.transits[2].start == 93 + 13  # previous release + window + margin
    frozen = seg.frozen_mask()
    for lo, hi in seg.windows:
        assert frozen[lo:hi + 1].all()


def test_no_grasp_no_transit():
    seg = segment_gripper(np.full(50, -1.0))
    assert seg.grasps == () and seg.transits == ()


# ---------------------------------------------------------------------------------------------- plans, labels
def _source(n=90, close=40):
    t = np.linspace(0, 1, n)
    pos = np.stack([0.3 * t, 0.1 * np.sin(3 * t), 1.0 + 0.05 * np.cos(2 * t)], axis=1)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return pos, quat, _command((-1, close), (1, n - close))


@settings(max_examples=30, deadline=None)
@given(phis, thetas, phis, thetas)
def test_plan_copies_interaction_windows_bit_for_bit(phi_a, theta_a, phi_c, theta_c):
    pos, quat, cmd = _source()
    seg = segment_gripper(cmd)
    samples = [ArcSample(seg.transits[0], phi_a, theta_a), ArcSample(seg.transits[1], phi_c, theta_c)]
    plan = build_plan(pos, quat, cmd, samples, Timing())
    copied = plan.source_frame >= 0
    src = plan.source_frame[copied]
    np.testing.assert_array_equal(plan.target_pos[:-1][copied], pos[src])
    np.testing.assert_array_equal(plan.gripper[copied], cmd[src])
    np.testing.assert_array_equal(plan.source_step[plan.source_step >= 0], src[plan.source_step[copied] >= 0])
    for lo, hi in seg.windows:  # every window frame appears once, in order, with the source's pose
        frames = np.flatnonzero(np.isin(plan.source_frame, np.arange(lo, hi + 1)))
        np.testing.assert_array_equal(plan.source_frame[frames], np.arange(lo, hi + 1))
    for span in plan.spans:  # each arc starts and ends on the source's transit endpoints
        tr = span.sample.transit
        np.testing.assert_array_equal(plan.target_pos[span.start], pos[tr.start])
        np.testing.assert_array_equal(plan.target_pos[span.end], pos[tr.end])


def test_unbent_plan_is_the_source():
    pos, quat, cmd = _source()
    seg = segment_gripper(cmd)
    plan = build_plan(pos, quat, cmd, [ArcSample(t, 0.0, 0.0) for t in seg.transits])
    np.testing.assert_array_equal(plan.source_step, np.arange(len(cmd)))
    assert plan.spans == []
    assert not make_label([ArcSample(t, 0.0, 0.0) for t in seg.transits], 4).any()


@pytest.mark.parametrize(("env_id", "size"), [
    ("SafeLibero-Spatial-Free-v0", 4), ("SafeLibero-Object-L1-v0", 4), ("SafeLibero-Goal-Free-v0", 8),
    ("SafeLibero-Long-L2-v0", 8), ("Newton-PickPlace-v0", 4),
])
def test_label_size_is_fixed_per_suite(env_id, size):
    from detaug_gym.envs.suites import suite_of_env

    assert DETAUG.label_size(suite_of_env(env_id)[0]) == size


def test_label_slots_follow_grasp_and_transit_kind():
    approach1 = Transit("approach", 1, 100, 130)
    label = make_label([ArcSample(approach1, 0.5, np.pi / 2), ArcSample(Transit("carry", 0, 40, 80), 0.4, 0.0)], 8)
    np.testing.assert_allclose(label, [0, 0, 0.4, 0, 0, 0.5, 0, 0], atol=1e-12)


def test_limit_takes_sources_task_by_task_not_file_order():
    from types import SimpleNamespace

    from detaug_gym.augment.runner import select_sources

    demos = [SimpleNamespace(name=f"demo_{i}", attrs={"task": i // 3}) for i in range(9)]  # 3 tasks x 3
    demos.append(SimpleNamespace(name="demo_aug", attrs={"task": 0, "augmented": True}))
    picked = [d.name for d in select_sources(demos, limit=4)]
    assert picked == ["demo_0", "demo_1", "demo_3", "demo_6"]  # every task first, then task 0 again
    assert len(select_sources(demos)) == 9  # augmented demos are never sources
