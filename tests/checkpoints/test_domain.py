"""Domains: measured from episodes, merged, and what of a scene lies outside a model's."""

from __future__ import annotations

import numpy as np
import pytest

from hrn_pyg.checkpoints.domain import (
    Domain,
    DomainError,
    check_scene,
    frames_domain,
    leaf_diameter,
    merge_all,
    outside,
    outside_line,
)
from hrn_pyg.data.graph import MATERIALS

SHAPES = Domain(pitches=(0.05,), materials=("rigid", "soft"), object_size=(0.2, 0.5), objects=(1, 3), speed=5.0)


def _cube(centre, side_leaves: int, pitch: float) -> np.ndarray:
    axis = (np.arange(side_leaves) - (side_leaves - 1) / 2) * pitch
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + np.asarray(centre)


def test_frames_domain_measures_pitch_materials_sizes_counts_and_speed():
    a, b = _cube([0, 0, 0.1], 2, 0.05), _cube([1, 0, 0.1], 3, 0.05)
    start = np.concatenate([a, b])
    frames = np.stack([start, start + [0, 0, -0.1]])  # every leaf falls 0.1 m in one step
    leaf_object = np.array([0] * len(a) + [1] * len(b))
    d = frames_domain(frames, leaf_object, np.array([0, 3]), pitch=0.05, dt=0.05, source="toy")
    assert d.pitches == (0.05,) and d.materials == ("rigid", "static") and d.objects == (1, 1)
    # the moving cube only: its leaves' diagonal plus one pitch
    assert d.object_size == pytest.approx((np.sqrt(3) * 0.05 + 0.05,) * 2)
    assert d.speed == pytest.approx(2.0) and d.episodes == 1 and d.sources == ("toy",)


def test_diameter_ignores_orientation_and_handles_flat_sets():
    cube = _cube([0, 0, 0], 4, 0.1)
    turn = np.array([[np.cos(0.7), -np.sin(0.7), 0], [np.sin(0.7), np.cos(0.7), 0], [0, 0, 1]])
    assert leaf_diameter(cube @ turn.T) == pytest.approx(leaf_diameter(cube)) == pytest.approx(np.sqrt(3) * 0.3)
    axis = np.arange(5) * 0.1
    sheet = np.stack([*np.meshgrid(axis, axis), np.zeros((5, 5))], -1).reshape(-1, 3)  # a flat 5 x 5 grid
    assert leaf_diameter(sheet) == pytest.approx(np.sqrt(2) * 0.4)
    assert leaf_diameter(np.zeros((1, 3))) == 0.0


def test_merge_spans_both_and_round_trips_through_json():
    other = Domain(pitches=(0.025,), materials=("cloth",), object_size=(0.1, 0.3), objects=(4, 4), speed=7.0,
                   episodes=2, sources=("x",))
    merged = merge_all([SHAPES, other])
    assert merged.pitches == (0.025, 0.05) and merged.materials == ("rigid", "soft", "cloth")
    assert merged.object_size == (0.1, 0.5) and merged.objects == (1, 4) and merged.speed == 7.0
    assert Domain.from_dict(merged.to_dict()) == merged
    assert merge_all([]) == Domain()


@pytest.mark.parametrize("raw, word", [
    ({"colour": 1}, "unknown fields"),
    ({"materials": ["gold"]}, "gold"),
    ({"object_size": [0.1]}, "malformed"),
    ([], "JSON object"),
])
def test_a_malformed_domain_is_one_clear_error(raw, word):
    with pytest.raises(ValueError, match=word):
        Domain.from_dict(raw)


def test_inside_says_nothing():
    scene = Domain(pitches=(0.05,), materials=("rigid",), object_size=(0.22, 0.55), objects=(2, 2), speed=6.0)
    assert outside(SHAPES, scene) == []
    assert check_scene("shapes.pt", SHAPES, scene, strict=True) is None
    assert check_scene("x.pt", None, Domain(pitches=(0.01,))) is None  # no recorded domain: no check


def test_pitch_line_names_both_pitches():
    line = check_scene("shapes.pt", SHAPES, Domain(pitches=(0.025,)))
    assert line == "shapes.pt was trained at pitch 0.05 m; this scene's pitch is 0.025 m (0.5x)"
    with pytest.raises(DomainError, match="pitch 0.05 m; this scene's pitch is 0.025 m"):
        check_scene("shapes.pt", SHAPES, Domain(pitches=(0.025,)), strict=True)


@pytest.mark.parametrize("scene, words", [
    (Domain(materials=("rigid", "cloth")), ["on rigid and soft objects", "this scene has cloth"]),
    (Domain(objects=(4, 4)), ["on 1-3 moving objects", "this scene has 4"]),
    (Domain(object_size=(0.3, 0.9)), ["on objects 0.2-0.5 m across", "one 0.9 m across (1.8x the largest)"]),
    (Domain(object_size=(0.1, 0.3)), ["one 0.1 m across (0.5x the smallest)"]),
    (Domain(speed=10.0), ["leaf speeds up to 5 m/s", "reaches 10 m/s (2x)"]),
])
def test_each_kind_of_outside_is_named_with_how_much(scene, words):
    found = outside(SHAPES, scene)
    assert len(found) == 1
    line = outside_line("shapes.pt", found)
    assert "\n" not in line and all(w in line for w in words), line


def test_several_at_once_stay_one_line():
    line = outside_line("m.pt", outside(SHAPES, Domain(pitches=(0.1,), materials=("cloth",))))
    assert line.count(";") == 1 and "pitch is 0.1 m" in line and "cloth" in line and "\n" not in line


def test_tolerances_keep_a_nearby_scene_inside():
    assert outside(SHAPES, Domain(pitches=(0.0502,), object_size=(0.17, 0.6), speed=7.0)) == []


def test_materials_are_the_package_materials():
    assert set(SHAPES.materials) <= set(MATERIALS)
