"""Object definitions: footprints, validation, loading, the generated object set."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from vistac.errors import ConfigError
from vistac.objects import (
    COM_SHRINK,
    FOOTPRINTS,
    HINGE_GAP_M,
    ObjectSpec,
    attachment,
    com_in_frames,
    footprint_polygon,
    generate_configurations,
    link_frames,
    load_object,
    match_links,
    object_from_dict,
    points_inside,
    polygon_area,
    polygon_centroid_covariance,
    redraw_parameters,
    split_configurations,
    write_configurations,
)

SIZES_MM = {
    "rect1": (90, 90), "rect2": (90, 112.5), "rect3": (135, 90),
    "tri1": (126, 126), "tri2": (151.2, 126), "tri3": (176.4, 126),
    "ellip1": (104.9, 104.9), "ellip2": (104.8, 131), "ellip3": (104.8, 157.2),
    "hexagon": (121.1, 104.9), "butter": (95.5, 157.3),
}  # fmt: skip

SKILL_OBJECTS = Path(__file__).resolve().parents[1] / "skills" / "objects"


def _link(**overrides: object) -> dict[str, object]:
    link: dict[str, object] = {"footprint": "rect1", "height_m": 0.05, "mass_kg": 0.5}
    link["friction"] = 0.3
    link.update(overrides)
    return link


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "thing.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("name", FOOTPRINTS)
def test_footprint_size_orientation_and_centroid(name: str) -> None:
    polygon = footprint_polygon(name)
    extent_mm = (polygon.max(axis=0) - polygon.min(axis=0)) * 1000.0
    np.testing.assert_allclose(extent_mm, SIZES_MM[name], atol=0.5)
    edges = np.roll(polygon, -1, axis=0) - polygon
    turns = (
        edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1]
        - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    )
    assert np.all(turns > 0), "counter-clockwise and convex"
    area = polygon_area(polygon)
    x, y = polygon[:, 0], polygon[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    centroid_x = ((x + np.roll(x, -1)) * cross).sum() / (6 * area)
    centroid_y = ((y + np.roll(y, -1)) * cross).sum() / (6 * area)
    np.testing.assert_allclose([centroid_x, centroid_y], 0.0, atol=1e-9)


def test_triangle_area_is_half_the_legs_product() -> None:
    assert polygon_area(footprint_polygon("tri2")) == pytest.approx(0.5 * 0.1512 * 0.126)


def test_a_uniform_point_in_a_right_triangle_and_a_shifted_rectangle() -> None:
    """Legs a, b: mean (a, b) / 3, variances a^2 / 18 and b^2 / 18, covariance -ab / 36; a
    w x h rectangle: its centre and w^2 / 12, h^2 / 12."""
    a, b = 0.12, 0.05
    mean, cov = polygon_centroid_covariance(np.array([[0.0, 0.0], [a, 0.0], [0.0, b]]))
    np.testing.assert_allclose(mean, [a / 3, b / 3])
    np.testing.assert_allclose(cov, [[a * a / 18, -a * b / 36], [-a * b / 36, b * b / 18]])
    w, h = 0.08, 0.03
    corners = np.array([[0.2, -0.1], [0.2 + w, -0.1], [0.2 + w, -0.1 + h], [0.2, -0.1 + h]])
    mean, cov = polygon_centroid_covariance(corners)
    np.testing.assert_allclose(mean, [0.2 + w / 2, -0.1 + h / 2])
    np.testing.assert_allclose(cov, np.diag([w * w / 12, h * h / 12]), atol=1e-15)


def test_com_outside_footprint_is_rejected_with_its_path() -> None:
    spec: dict[str, Any] = {"name": "x", "type": "homogeneous"}
    spec["links"] = [_link(com_m=[0.05, 0.0])]
    spec["pose"] = [0, 0.45, 0]
    with pytest.raises(ConfigError) as error:
        _validate(spec)
    assert "links[0]" in str(error.value)
    assert "outside footprint 'rect1'" in str(error.value)


def _validate(data: dict[str, Any]) -> ObjectSpec:
    return object_from_dict(data, "inline")


def test_load_errors_name_file_and_yaml_path(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        "name: x\ntype: homogeneous\npose: [0, 0.45, 0]\nlinks:\n"
        "  - {footprint: rect1, height_m: 0.05, mass_kg: 3.0, friction: 0.3}\n",
    )
    with pytest.raises(ConfigError) as error:
        load_object(path)
    message = str(error.value)
    assert str(path) in message
    assert "links[0].mass_kg" in message
    assert "less than or equal to 1.6" in message


def test_misspelt_key_names_the_known_one() -> None:
    spec: dict[str, Any] = {"name": "x", "type": "homogeneous", "pose": [0, 0.45, 0]}
    spec["links"] = [_link(mass=0.5)]
    with pytest.raises(ConfigError) as error:
        _validate(spec)
    assert "links[0].mass: Extra inputs are not permitted (did you mean 'mass_kg'?)" in str(
        error.value
    )


def test_load_rejects_unknown_footprint_and_bad_yaml(tmp_path: Path) -> None:
    bad_footprint = _write(
        tmp_path,
        "name: x\ntype: homogeneous\npose: [0, 0.45, 0]\nlinks:\n"
        "  - {footprint: circle, height_m: 0.05, mass_kg: 1.0, friction: 0.3}\n",
    )
    with pytest.raises(ConfigError, match=r"links\[0\]\.footprint"):
        load_object(bad_footprint)
    with pytest.raises(ConfigError) as malformed:
        load_object(_write(tmp_path, "name: [unclosed\n"))
    assert len(str(malformed.value).splitlines()) == 1
    assert ": malformed YAML: line 2, column 1: expected ',' or ']'" in str(malformed.value)
    with pytest.raises(ConfigError, match="duplicate key 'name'"):
        load_object(_write(tmp_path, "name: a\nname: b\n"))
    with pytest.raises(ConfigError, match="must be a mapping"):
        load_object(_write(tmp_path, "- 1\n- 2\n"))


def test_structure_rules() -> None:
    two_links = [_link(), _link()]
    base = {"name": "x", "pose": [0, 0.45, 0]}
    with pytest.raises(ConfigError, match="articulated objects"):
        _validate({**base, "type": "articulated", "links": two_links})
    with pytest.raises(ConfigError, match="has 2 link"):
        _validate({**base, "type": "heterogeneous", "links": [_link()]})
    with pytest.raises(ConfigError, match=r"joint\.friction_nm"):
        _validate(
            {**base, "type": "articulated", "links": two_links, "joint": {"friction_nm": 0.9}}
        )


def test_articulated_attachment_places_hinge_between_touching_rectangles() -> None:
    spec = _validate(
        {
            "name": "x", "type": "articulated", "links": [_link(), _link()],
            "pose": [0.1, 0.4, np.pi / 2], "joint": {"friction_nm": 0.1},
        }
    )  # fmt: skip
    offset, hinge = attachment(spec)
    np.testing.assert_allclose(offset, [0.09 + HINGE_GAP_M, 0.0])
    assert hinge is not None
    np.testing.assert_allclose(hinge, [0.045 + HINGE_GAP_M / 2, 0.0])
    # Link 0 turned by 90 degrees: link 1 sits along world +y.
    np.testing.assert_allclose(link_frames(spec)[1], [0.1, 0.4 + 0.094, np.pi / 2], atol=1e-12)


def test_generator_counts_ranges_and_reproducibility() -> None:
    specs = generate_configurations(seed=3)
    assert [
        sum(s.type == kind for s in specs)
        for kind in ("homogeneous", "heterogeneous", "articulated")
    ] == [40, 40, 40]
    assert len({s.name for s in specs}) == 120
    assert all(len(s.links) == (1 if s.type == "homogeneous" else 2) for s in specs)
    assert all((s.joint is not None) == (s.type == "articulated") for s in specs)
    masses = np.array([link.mass_kg for s in specs for link in s.links])
    assert masses.min() >= 0.2 and masses.max() <= 1.6 and masses.std() > 0.3
    for spec in specs:
        for link in spec.links:
            assert points_inside(footprint_polygon(link.footprint), np.array([link.com_m]))[0]
    assert generate_configurations(seed=3) == specs
    assert generate_configurations(seed=4) != specs



def test_redrawn_parameters_keep_the_object_and_spread_as_the_set_does() -> None:
    spec = generate_configurations(seed=3)[100]  # articulated
    rng = np.random.default_rng(0)
    draws = [redraw_parameters(spec, rng) for _ in range(400)]
    for draw in draws[:20]:
        ObjectSpec.model_validate(draw.model_dump())  # every value valid: CoM inside, ranges
        assert (draw.name, draw.pose, draw.type) == (spec.name, spec.pose, spec.type)
        assert [(a.footprint, a.height_m) for a in draw.links] == [
            (a.footprint, a.height_m) for a in spec.links]
        assert points_inside(COM_SHRINK * draw.links[1].polygon(),
                             np.array([draw.links[1].com_m]))[0]  # fmt: skip
    masses = np.array([d.links[0].mass_kg for d in draws])
    joints = np.array([d.joint.friction_nm for d in draws if d.joint is not None])
    assert masses.mean() == pytest.approx(0.9, abs=0.05) and masses.std() == pytest.approx(
        1.4 / np.sqrt(12), rel=0.1)
    assert len(joints) == 400 and joints.mean() == pytest.approx(0.25, abs=0.02)
    coms = np.array([d.links[0].com_m for d in draws])
    centre, _ = polygon_centroid_covariance(COM_SHRINK * spec.links[0].polygon())
    np.testing.assert_allclose(coms.mean(axis=0), centre, atol=0.004)
    assert redraw_parameters(spec, np.random.default_rng(7)) == redraw_parameters(
        spec, np.random.default_rng(7)) != redraw_parameters(spec, np.random.default_rng(8))

def test_split_is_stratified_disjoint_and_reproducible() -> None:
    specs = generate_configurations(seed=1)
    split = split_configurations(specs, seed=1)
    assert {name: len(names) for name, names in split.items()} == {
        "train": 96,
        "val": 12,
        "test": 12,
    }
    kinds = {s.name: s.type for s in specs}
    for names in split.values():
        assert {kinds[n] for n in names} == {"homogeneous", "heterogeneous", "articulated"}
    assert sorted(name for names in split.values() for name in names) == sorted(kinds)
    assert split_configurations(specs, seed=1) == split
    assert split_configurations(specs, seed=2) != split


def test_write_configurations_round_trips(tmp_path: Path) -> None:
    split = write_configurations(seed=5, out_dir=tmp_path)
    specs = {s.name: s for s in generate_configurations(seed=5)}
    assert len(list(tmp_path.glob("*.yaml"))) == 120
    assert (tmp_path / "split.json").is_file()
    for name in split["test"]:
        assert load_object(tmp_path / f"{name}.yaml") == specs[name]


def test_skill_object_library_loads() -> None:
    names = {path.stem for path in SKILL_OBJECTS.glob("*.yaml")}
    assert names >= {*FOOTPRINTS, "hetero_rect_tri", "artic_rect_rect"}
    for path in SKILL_OBJECTS.glob("*.yaml"):
        assert load_object(path).name == path.stem


def test_links_match_by_position_and_the_com_moves_into_their_frames() -> None:
    # True link 0 at the origin, link 1 at (0.1, 0) turned by 90 deg with its CoM 0.02 m
    # along its x, so at (0.1, 0.02). Fitted frame 0 lies near link 1, 0.01 m along +y from
    # its origin, turned by -90 deg: there that CoM is 0.01 m along -x. Fitted frame 1 lies
    # 1 mm from link 0's origin along x, turned by pi: link 0's CoM (0.01, 0) is 9 mm along
    # its -x.
    true_poses = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, np.pi / 2]])
    frames = np.array([[0.1, 0.01, -np.pi / 2], [0.001, 0.0, np.pi]])
    links = match_links(frames[:, :2], true_poses[:, :2])
    assert links == {0: 1, 1: 0}
    truth = {"m_0": 0.5, "com_x_0": 0.01, "com_y_0": 0.0, "m_1": 1.0, "com_x_1": 0.02,
             "com_y_1": 0.0, "f_j_0": 0.1}  # fmt: skip
    moved = com_in_frames(truth, links, frames, true_poses)
    assert moved["com_x_1"] == pytest.approx(-0.01) and moved["com_y_1"] == pytest.approx(0.0)
    assert moved["com_x_0"] == pytest.approx(-0.009) and moved["com_y_0"] == pytest.approx(0.0)
    assert (moved["m_0"], moved["m_1"], moved["f_j_0"]) == (0.5, 1.0, 0.1)
    # one frame for two links: link 0 is left unmatched and its CoM dropped
    single = match_links(frames[:1, :2], true_poses[:, :2])
    assert single == {0: 1}
    assert "com_x_0" not in com_in_frames(truth, single, frames[:1], true_poses)
    # two frames for one link: the nearer frame is matched, whichever comes first
    assert match_links(np.array([[0.3, 0.2], [0.0, 0.45]]), np.array([[0.0, 0.45]])) == {1: 0}
    assert match_links(np.zeros((0, 2)), true_poses[:, :2]) == {}
