"""The one reader layer of structured user inputs (``io/preflight``'s ``read_text`` /
``read_json`` and the URDF / MJCF structure checks): deep, binary, oversized or structurally
broken files are one :class:`InputError` line naming the file, the element and what is
expected, before any work, and the file is left as it was. Library calls, no subprocess."""

import json
import os
from pathlib import Path

import pytest

from jaxmocap.body import load_body, read_roles_file
from jaxmocap.errors import InputError
from jaxmocap.experiment.config import ExperimentError, _split_names, load_config
from jaxmocap.io.garment_file import load_garment
from jaxmocap.io.preflight import MAX_JSON_DEPTH, read_json, read_text

DEEP = "[" * 100_000 + "]" * 100_000  # RecursionError in json.loads
DEEPISH = json.dumps(json.loads("[" * (MAX_JSON_DEPTH + 1) + "]" * (MAX_JSON_DEPTH + 1)))


@pytest.fixture(scope="module")
def body():
    from jaxmocap.body import default_body

    return default_body()


def _one_line(exc: pytest.ExceptionInfo, *parts: str) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, msg
    for p in parts:
        assert p in msg, msg
    return msg


def _unchanged(path: Path, before: bytes) -> None:
    assert path.read_bytes() == before


@pytest.mark.parametrize("content, match", [
    (DEEP, "nested too deeply"),
    (DEEPISH, "nested too deeply"),
    (bytes(range(256)) * 8, "not a text file"),
    (b"", "not valid JSON"),
    ("{\"colours\": [1, 2,}", "not valid JSON"),
])
def test_json_readers_refuse_in_one_line(tmp_path, body, content, match):
    """Every JSON config the user gives goes through read_json: garment, roles, experiment
    configuration and split (each with its own error class and 'expected' text)."""
    data = content.encode() if isinstance(content, str) else content
    for name, call, expected in [
        ("garment.json", lambda p: load_garment(p, body), "garment.json"),
        ("body.roles.json", read_roles_file, "roles file"),
        ("exp.json", load_config, "experiment configuration"),
        ("split.json", lambda p: _split_names(p, None), "split file"),
    ]:
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(InputError) as e:
            call(path)
        _one_line(e, str(path.resolve() if name == "exp.json" else path), match, expected)
        _unchanged(path, data)


def test_experiment_errors_keep_their_class(tmp_path):
    split = tmp_path / "split.json"
    split.write_bytes(os.urandom(4096))
    with pytest.raises(ExperimentError, match="not a text file"):
        _split_names(split, None)
    toml = tmp_path / "exp.toml"
    toml.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ExperimentError) as e:
        load_config(toml)
    _one_line(e, "exp.toml", "nested too deeply")


def test_read_text_limits(tmp_path):
    big = tmp_path / "big.json"
    big.write_text("[" + "0," * 600 + "0]")
    with pytest.raises(InputError) as e:
        read_text(big, "a small file", max_bytes=1000)
    _one_line(e, str(big), "too large", "at most 1,000", "a small file")
    assert read_json(big, "x") == [0] * 601
    with pytest.raises(InputError) as e:
        read_json(tmp_path, "a file")
    _one_line(e, "is a folder")
    with pytest.raises(InputError) as e:
        read_json(tmp_path / "nope.json", "a file")
    _one_line(e, "no such file")
    ok = tmp_path / "ok.json"
    ok.write_text(json.dumps({"a": [[[1]]]}))
    assert read_json(ok, "x") == {"a": [[[1]]]}


# ----------------------------------------------------------------------------- URDF / MJCF


def _link(n):
    return f'<link name="{n}"/>'


def _joint(n, parent, child, jtype="revolute"):
    return (f'<joint name="{n}" type="{jtype}"><parent link="{parent}"/>'
            f'<child link="{child}"/></joint>')


def _robot(*parts):
    return '<robot name="r">' + "".join(parts) + "</robot>"


ABC = (_link("a"), _link("b"), _link("c"))

URDF_CASES = {
    "loop": (_robot(*ABC, _joint("j1", "b", "a"), _joint("j2", "c", "b"),
                    _joint("j3", "a", "c")), ["form a loop", "expected a tree"]),
    "two_parents": (_robot(*ABC, _joint("j1", "a", "b"), _joint("j2", "c", "b")),
                    ["<joint name='j2'>", "'b' is already the child of joint 'j1'"]),
    "no_parent": (_robot(*ABC[:2], '<joint name="j" type="revolute"><child link="b"/></joint>'),
                  ["<joint name='j'>", "no <parent>", 'expected exactly one <parent link="...">']),
    "no_child": (_robot(*ABC[:2], '<joint name="j" type="fixed"><parent link="a"/></joint>'),
                 ["<joint name='j'>", "no <child>"]),
    "missing_parent": (_robot(*ABC[:2], _joint("j1", "ghost", "b")),
                       ["<parent link='ghost'>", "no link named 'ghost'", "links: a, b"]),
    "missing_child": (_robot(*ABC[:2], _joint("j1", "a", "b"), _joint("j2", "b", "phantom")),
                      ["<joint name='j2'>", "no link named 'phantom'"]),
    "duplicate_link": (_robot(_link("a"), _link("b"), _link("a"), _joint("j", "a", "b")),
                       ["<link name='a'> is defined twice"]),
    "self_joint": (_robot(*ABC[:2], _joint("j", "a", "a")), ["joins link 'a' to itself"]),
    "two_roots": (_robot(*ABC, _joint("j", "a", "b")), ["'a', 'c' all have no parent joint"]),
    "unnamed_link": (_robot('<link/>', _link("b")), ["<link> #0 has no name"]),
    "bad_type": (_robot(*ABC[:2], _joint("j", "a", "b", "hinge")), ["has type 'hinge'"]),
    "bad_number": (_robot(*ABC[:2], '<joint name="j" type="revolute"><parent link="a"/>'
                          '<child link="b"/><origin xyz="0 zero 1"/></joint>'),
                   ["joint 'j' <origin xyz>", "expected 3 finite numbers"]),
    "malformed": ('<robot><link name="a"></robot>', ["not valid XML", "line 1"]),
    "not_robot": ("<mujoco/>", ["root element is <mujoco>, expected <robot>"]),
}


def test_urdf_structure_refused_before_pytorch_kinematics(tmp_path, monkeypatch):
    import pytorch_kinematics as pk

    def never(*a, **k):
        raise AssertionError("pytorch-kinematics saw a malformed URDF")

    monkeypatch.setattr(pk, "build_chain_from_urdf", never)
    for name, (text, parts) in URDF_CASES.items():
        path = tmp_path / f"{name}.urdf"
        path.write_text(text)
        with pytest.raises(InputError) as e:
            load_body(path)
        _one_line(e, str(path), *parts)
        _unchanged(path, text.encode())


def test_binary_and_huge_models(tmp_path, monkeypatch):
    import jaxmocap.body.urdf as urdf

    for suffix in (".urdf", ".xml"):
        path = tmp_path / f"random{suffix}"
        path.write_bytes(bytes(range(128, 256)) * 4)
        with pytest.raises(InputError) as e:
            load_body(path)
        _one_line(e, str(path), "not a text file")
    monkeypatch.setattr(urdf, "MAX_MODEL_BYTES", 100)
    path = tmp_path / "big.urdf"
    path.write_text(_robot(*ABC, _joint("j1", "a", "b"), _joint("j2", "a", "c")))
    with pytest.raises(InputError) as e:
        load_body(path)
    _one_line(e, str(path), "too large", "at most 100")


def test_valid_urdf_still_loads(tmp_path):
    """The checks pass a correct tree (links and joints in any order; spherical joints)."""
    text = _robot(_joint("j2", "b", "c", "spherical"), *ABC, _joint("j1", "a", "b"))
    path = tmp_path / "ok.urdf"
    path.write_text(text)
    from jaxmocap.body.urdf import check_urdf_structure, prepare_urdf

    robot, _ = prepare_urdf(text, str(path))
    check_urdf_structure(robot, str(path))  # the expanded tree is a tree too
    assert [link.get("name") for link in robot.findall("link")][:3] == ["c__x", "c__y", "a"]
