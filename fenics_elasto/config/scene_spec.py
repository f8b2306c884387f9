"""The schema of a scene spec (``fenics-elasto scene``), and reading one."""

from __future__ import annotations

from pathlib import Path

from fenics_elasto.config.schema import (REQUIRED, Boolean, Choice, GroupName, Key, Labels, Named, Names, Number, String,
                                         Table, Vector, Where, show)
from fenics_elasto.config.toml import apply_overrides, read_toml

def _check_spec(spec: dict, where: Where) -> dict:
    """Group names must not clash; a box or ellipsoid needs something to surround."""
    owners: dict[str, str] = {}

    def claim(name, at: Where, role: str):
        if name in owners:
            at.fail(f"group name {show(name)} ({role}) clashes with {owners[name]}")
        owners[name] = f"the {role} of {at.path()}" if at.keys else role

    claim("outer", where, "the body's outer boundary")
    claim(spec["body"]["material"], where.at("body").at("material"), "cell group")
    for name in spec["regions"]:
        claim(name, where.at("regions").at(name), "cell group")
        claim(f"{name}_surface", where.at("regions").at(name), "facet group")
    for section in ("cavities", "patches"):
        for name in spec[section]:
            claim(name, where.at(section).at(name), "facet group")
    for shape in ("box", "ellipsoid"):
        if spec["body"][shape] is not None and not (spec["regions"] or spec["cavities"]):
            where.at("body").at(shape).fail("surrounds the regions and cavities, but there are none")
    return _check_labels(spec, where) if spec["labels"] else _check_no_labels(spec, where)


def _check_no_labels(spec: dict, where: Where) -> dict:
    """Without a [labels] image, every shape comes from a surface file (or a box)."""
    for at, table in _shapes(spec, where):
        if table.get("label") is not None:
            at.at("label").fail("a label needs a label-map image: add [labels] image = \"...\"")
    return spec


def _check_labels(spec: dict, where: Where) -> dict:
    """With a [labels] image every shape is a set of labels that nest: regions within
    the body's labels, cavities outside them, no label used twice."""
    owner: dict[int, str] = {}
    for at, table in _shapes(spec, where):
        if table.get("surface") is not None:
            at.at("surface").fail("the scene comes from the [labels] image: give label = N, not a surface file")
        if at.keys[0] == "body":  # a region's labels are the body's too
            continue
        for value in table.get("label") or []:
            if value in owner:
                at.at("label").fail(f"label {value} is also {owner[value]}'s; a label belongs to one region or cavity")
            owner[value] = at.path()
    body = spec["body"]["label"]
    if body is not None:
        for kind in ("regions", "cavities"):
            for name, table in spec[kind].items():
                outside = [v for v in table["label"] if (v in body) != (kind == "regions")]
                if outside:
                    rule = "not one of body.label: a region is part of the body" if kind == "regions" else \
                        "one of body.label: a cavity is a hole in the body, not part of it"
                    where.at(kind).at(name).at("label").fail(f"label {outside[0]} is {rule} ({body})")
    return spec


def _shapes(spec: dict, where: Where):
    """(where, table) of every region and cavity, and of the body."""
    for kind in ("regions", "cavities"):
        for name, table in spec[kind].items():
            yield where.at(kind).at(name), table
    yield where.at("body"), spec["body"]


def _margin():
    return Table({"margin": Key(Number(gt=0), REQUIRED)})


SCENE_SPEC = Table({
    "units": Key(Choice("mm", "cm", "m"), "mm"),
    "size": Key(Number(gt=0)),
    "organ_size": Key(Number(gt=0)),
    "labels": Key(Table({"image": Key(String("a label-map image"), REQUIRED)})),
    "body": Key(Table({
        "surface": Key(String("a surface file")), "label": Key(Labels()), "box": Key(_margin()),
        "ellipsoid": Key(_margin()), "material": Key(GroupName(), "tissue"),
    }, exclusive=[("surface", "label", "box", "ellipsoid")], one_of=("surface", "label", "box", "ellipsoid"),
        expected="a table {surface, label, box or ellipsoid; material}"), REQUIRED),
    "regions": Key(Named(Table({"surface": Key(Names("surface file", nonempty=True)), "label": Key(Labels())},
                               exclusive=[("surface", "label")], one_of=("surface", "label")),
                         "[regions.NAME] tables", group_names=True), {}),
    "cavities": Key(Named(Table({"surface": Key(String("a surface file")), "label": Key(Labels())},
                                exclusive=[("surface", "label")], one_of=("surface", "label")),
                          "[cavities.NAME] tables", group_names=True), {}),
    "patches": Key(Named(Table({"side": Key(Table({
        "point": Key(Vector((3,)), REQUIRED), "normal": Key(Vector((3,), nonzero=True), REQUIRED),
    }, expected="a table {point, normal}"), REQUIRED), "loaded": Key(Boolean(), False)},
        expected="a table {side, loaded}"), "[patches.NAME] tables", group_names=True), {}),
}, after=_check_spec)


def validate_scene_spec(raw: dict, source: str = "scene.toml", overridden: dict | None = None) -> dict:
    return SCENE_SPEC.check(raw, Where(str(source), (), overridden or {}))


def read_scene_spec(path, overrides=()) -> dict:
    """Read, override and check a scene spec (``fenics-elasto scene``): the normalised spec."""
    raw = read_toml(Path(path), "scene spec")
    overridden = apply_overrides(raw, overrides, SCENE_SPEC, str(path))
    return validate_scene_spec(raw, str(path), overridden)
