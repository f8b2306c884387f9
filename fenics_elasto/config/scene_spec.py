"""The schema of a scene spec (``fenics-elasto scene``), and reading one."""

from __future__ import annotations

from pathlib import Path

from fenics_elasto.config.schema import (REQUIRED, Choice, GroupName, Key, Named, Names, Number, String, Table,
                                         Vector, Where, show)
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
    return spec


def _margin():
    return Table({"margin": Key(Number(gt=0), REQUIRED)})


SCENE_SPEC = Table({
    "units": Key(Choice("mm", "cm", "m"), "mm"),
    "size": Key(Number(gt=0)),
    "organ_size": Key(Number(gt=0)),
    "body": Key(Table({
        "surface": Key(String("a surface file")), "box": Key(_margin()), "ellipsoid": Key(_margin()),
        "material": Key(GroupName(), "tissue"),
    }, exclusive=[("surface", "box", "ellipsoid")], one_of=("surface", "box", "ellipsoid"),
        expected="a table {surface, box or ellipsoid; material}"), REQUIRED),
    "regions": Key(Named(Table({"surface": Key(Names("surface file", nonempty=True), REQUIRED)}), "[regions.NAME] tables",
                         group_names=True), {}),
    "cavities": Key(Named(Table({"surface": Key(String("a surface file"), REQUIRED)}), "[cavities.NAME] tables",
                          group_names=True), {}),
    "patches": Key(Named(Table({"side": Key(Table({
        "point": Key(Vector((3,)), REQUIRED), "normal": Key(Vector((3,), nonzero=True), REQUIRED),
    }, expected="a table {point, normal}"), REQUIRED)}), "[patches.NAME] tables", group_names=True), {}),
}, after=_check_spec)


def validate_scene_spec(raw: dict, source: str = "scene.toml", overridden: dict | None = None) -> dict:
    return SCENE_SPEC.check(raw, Where(str(source), (), overridden or {}))


def read_scene_spec(path, overrides=()) -> dict:
    """Read, override and check a scene spec (``fenics-elasto scene``): the normalised spec."""
    raw = read_toml(Path(path), "scene spec")
    overridden = apply_overrides(raw, overrides, SCENE_SPEC, str(path))
    return validate_scene_spec(raw, str(path), overridden)
