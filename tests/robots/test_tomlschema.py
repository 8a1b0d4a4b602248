"""The one TOML validator (labcal.tomlschema): kinds, shapes, defaults, unknown keys, and messages naming the key."""

from __future__ import annotations

import pytest

from labcal.tomlschema import Key, SchemaError, Table, read_toml, validate

INNER = Table({"xyz": Key("vector", shape=(3,), unit="m", default=[0.0, 0.0, 0.0]), "mass": Key("number")})
SCHEMA = Table(
    {
        "name": Key("str", required=True),
        "count": Key("int", default=2),
        "flag": Key("bool", default=False),
        "unit": Key("str", choices=("m", "mm"), default="m"),
        "points": Key("vectors", shape=(None, 3)),
        "matrix": Key("vectors", shape=("n", "n")),
        "columns": Key("strings", shape=(2,)),
        "tool": Key("table", table=INNER, default={}),
        "rows": Key("tables", table=INNER, min_items=1),
        "gain": Key("number", check=lambda v: None if v > 0 else f"must be > 0, got {v}"),
    },
    name="test file",
)


class MyError(SchemaError):
    pass


def test_defaults_are_filled_and_numbers_become_floats():
    doc = validate({"name": "a", "points": [[1, 2, 3]], "rows": [{"mass": 2}]}, SCHEMA, source="f.toml")
    assert doc == {
        "name": "a",
        "count": 2,
        "flag": False,
        "unit": "m",
        "points": [[1.0, 2.0, 3.0]],
        "tool": {"xyz": [0.0, 0.0, 0.0]},
        "rows": [{"xyz": [0.0, 0.0, 0.0], "mass": 2.0}],
    }
    assert isinstance(doc["points"][0][0], float)


@pytest.mark.parametrize(
    "data, message",
    [
        ({}, r"^f\.toml: name is missing \(required\)$"),
        ({"name": 3}, r"name must be a string, got 3"),
        ({"name": "a", "count": 2.5}, r"count must be an integer, got 2\.5"),
        ({"name": "a", "count": True}, r"count must be an integer, got True"),
        ({"name": "a", "gain": True}, r"gain must be a finite number, got True"),
        ({"name": "a", "gain": float("nan")}, r"gain must be a finite number, got nan"),
        ({"name": "a", "gain": -1}, r"gain must be > 0, got -1\.0"),
        ({"name": "a", "unit": "cm"}, r"unit must be one of 'm', 'mm', got 'cm'"),
        ({"name": "a", "unit": "mn"}, r"got 'mn' \(did you mean 'm'\?\)"),
        ({"name": "a", "points": [[1, 2]]}, r"points must be a list of rows of 3 numbers, got \[\[1, 2\]\]"),
        ({"name": "a", "matrix": [[1, 0], [0, 1]]}, r"matrix must be 3 rows of 3 numbers"),
        ({"name": "a", "columns": ["a", 1]}, r"columns must be a list of 2 strings"),
        ({"name": "a", "tool": {"xyz": [0, 0]}}, r"tool\.xyz must be a list of 3 numbers \(m\), got \[0, 0\]"),
        ({"name": "a", "tool": 3}, r"tool must be a table, got 3"),
        ({"name": "a", "rows": []}, r"rows needs at least one \[\[rows\]\] table, got \[\]"),
        ({"name": "a", "rows": [{}, {"mas": 1}]}, r"rows\[2\]: unknown key 'mas' \(did you mean 'mass'\?\)"),
        ({"name": "a", "nmae": "b"}, r"test file: unknown key 'nmae' \(did you mean 'name'\?\); allowed: columns"),
    ],
)
def test_every_error_names_file_table_and_key(data, message):
    with pytest.raises(MyError, match=message) as info:
        validate(data, SCHEMA, source="f.toml", error=MyError, dims={"n": 3})
    assert str(info.value).startswith("f.toml: ") and isinstance(info.value, ValueError)


def test_read_toml_names_the_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("name = \n")
    with pytest.raises(MyError, match=r"bad\.toml: not valid TOML"):
        read_toml(bad, MyError)
    with pytest.raises(MyError, match=r"nope\.toml: cannot read thing"):
        read_toml(tmp_path / "nope.toml", MyError, "thing")
