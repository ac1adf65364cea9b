"""The launch file names only executables and parameter files that exist.

launch / launch_ros are not installable from PyPI, so the file is checked as source: every
``Node(...)`` in launch/*.launch.py must name an executable declared as a console script in
setup.py, every YAML it names must exist in config/, and the YAML's top-level key must be
the node's name (else ROS silently applies none of its parameters).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml


def _node_calls(tree: ast.AST) -> list[ast.Call]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and isinstance(n.func, ast.Name) and n.func.id == "Node"]


def _kw(call: ast.Call, name: str) -> ast.expr | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


def _yaml_names(node: ast.AST) -> list[str]:
    return [c.value for c in ast.walk(node) if isinstance(c, ast.Constant)
            and isinstance(c.value, str) and c.value.endswith((".yaml", ".yml"))]


def _console_scripts(repo_root: Path) -> set[str]:
    tree = ast.parse((repo_root / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values, strict=True):
                if isinstance(key, ast.Constant) and key.value == "console_scripts":
                    entries = ast.literal_eval(value)
                    return {e.split("=")[0].strip() for e in entries}
    raise AssertionError("setup.py declares no console_scripts")


def _value(expr: ast.expr | None, constants: dict[str, object]) -> object:
    """A literal, or a module-level constant it names."""
    if isinstance(expr, ast.Name):
        return constants[expr.id]
    return ast.literal_eval(expr) if expr is not None else None


def _launch_files(repo_root: Path) -> list[Path]:
    return sorted((repo_root / "launch").glob("*.launch.py"))


def test_there_is_a_launch_file_with_the_three_nodes(repo_root):
    files = _launch_files(repo_root)
    assert files, "no launch/*.launch.py"
    names = set()
    for f in files:
        for call in _node_calls(ast.parse(f.read_text())):
            exe = _kw(call, "executable")
            assert isinstance(exe, ast.Constant), f"{f.name}: executable must be a literal"
            names.add(exe.value)
    assert {"serial_bridge_node", "vo_node", "predictor_node"} <= names


@pytest.mark.parametrize("launch_name", ["asgp.launch.py"])
def test_executables_and_parameter_files_exist(repo_root, launch_name):
    path = repo_root / "launch" / launch_name
    tree = ast.parse(path.read_text())
    scripts = _console_scripts(repo_root)
    calls = _node_calls(tree)
    assert calls
    constants = {t.id: n.value.value for n in tree.body if isinstance(n, ast.Assign)
                 for t in n.targets if isinstance(t, ast.Name)
                 and isinstance(n.value, ast.Constant)}
    for call in calls:
        exe = ast.literal_eval(_kw(call, "executable"))
        assert _value(_kw(call, "package"), constants) == "asgp_ros"
        assert exe in scripts, f"{launch_name}: executable {exe!r} is not in setup.py"
        name = _kw(call, "name")
        node_name = ast.literal_eval(name) if name is not None else exe
        params = _kw(call, "parameters")
        assert params is not None, f"{exe}: no parameters"
        yamls = _yaml_names(params)
        assert yamls, f"{exe}: names no YAML parameter file"
        for y in yamls:
            cfg = repo_root / "config" / y
            assert cfg.is_file(), f"{launch_name}: {exe} uses config/{y}, which does not exist"
            data = yaml.safe_load(cfg.read_text())
            # a bare node name is the node in / only: under namespace:=chair1 rcl would
            # apply none of the file's values, without a word
            key = f"/**/{node_name}"
            assert isinstance(data, dict) and ("/**" in data or key in data), (
                f"config/{y} has top-level keys {sorted(data)}, not {key!r} (or '/**')"
            )
            section = data.get(key, data.get("/**"))
            assert "ros__parameters" in section, f"config/{y}: no ros__parameters"


def test_string_arguments_reach_the_nodes_as_strings(repo_root):
    """launch_ros reads a bare LaunchConfiguration in a node's parameters as YAML: a model
    path ``chair #2.npz`` reached the node as ``chair``, ``run: 2.npz`` aborted the launch.
    Every argument given as a node parameter goes through ``_text`` (a ParameterValue of
    value_type str)."""
    tree = ast.parse((repo_root / "launch" / "asgp.launch.py").read_text())
    checked = 0
    for call in _node_calls(tree):
        for d in ast.walk(_kw(call, "parameters")):
            if not isinstance(d, ast.Dict):
                continue
            for key, value in zip(d.keys, d.values, strict=True):
                if isinstance(key, ast.Constant) and key.value in ("model_path", "port"):
                    assert isinstance(value, ast.Call) and isinstance(value.func, ast.Name) \
                        and value.func.id == "_text", ast.unparse(value)
                    checked += 1
    assert checked == 3
    text = ast.unparse(next(f for f in tree.body if isinstance(f, ast.FunctionDef)
                            and f.name == "_text"))
    assert "ParameterValue(LaunchConfiguration(name), value_type=str)" in text


def test_predictor_yaml_matches_the_node_parameters(repo_root):
    pytest.importorskip("rclpy")
    from asgp_ros.nodes.predictor_node import SPECS, PredictorNodeParams

    data = yaml.safe_load((repo_root / "config" / "predictor.yaml").read_text())
    params = {}
    for name, value in data["/**/predictor_node"]["ros__parameters"].items():
        if isinstance(value, dict):  # nested parameters: adapt: {enabled: ...} = adapt.enabled
            params.update({f"{name}.{key}": v for key, v in value.items()})
        else:
            params[name] = value
    params.pop("use_sim_time", None)
    assert set(params) == set(SPECS)
    fields = {name: name.replace(".", "_") for name in params}
    defaults = PredictorNodeParams.__dataclass_fields__
    for name, value in params.items():
        # same type as the declared default (ROS refuses 2 for a double parameter)
        assert type(value) is type(defaults[fields[name]].default), name
    # the file's values (with a model path) validate
    PredictorNodeParams(**{**{fields[k]: v for k, v in params.items()},
                           "model_path": "chair.npz"})
