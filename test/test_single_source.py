"""One source of truth for each idea: every constant below is defined once in asgp_ros, and
the YAML files and the README are checked against that definition.

The scan reads the code (not comments, docstrings or messages) of every module of the
package. A module that still holds its own copy, and is waiting to switch to the one
definition, is listed in ``PENDING`` with what it must import instead; a pending entry that
has been fixed fails ``test_pending_copies_still_exist``, so that the list only shrinks.
"""

from __future__ import annotations

import ast
import functools
import io
import re
import tokenize
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml

from asgp_ros.common import topics
from asgp_ros.core.features import CHANNELS
from asgp_ros.core.metrics import CHI2_2DOF_95, HORIZONS_S, THRESHOLD_M, horizon_key
from asgp_ros.core.models import BUILTIN_KINDS

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "asgp_ros"

#: The topic names of asgp_ros.common.topics (relative; a bag holds them with a leading "/").
TOPIC_NAMES = {value for name, value in vars(topics).items()
               if name.isupper() and isinstance(value, str) and not name.startswith("BAG_")}
KIND_NAMES = {k.name for k in BUILTIN_KINDS}

#: constant -> {module (relative to asgp_ros/): the one definition it must use instead}.
#: These modules belong to other work in progress; remove an entry once it is switched.
PENDING: dict[str, dict[str, str]] = {}


# ----------------------------------------------------------------------------- the scan
@functools.cache
def _modules() -> tuple[tuple[str, ast.Module, str], ...]:
    """(path relative to asgp_ros/, syntax tree, code without comments and strings) of
    every module."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text()
        tokens = tokenize.generate_tokens(io.StringIO(text).readline)
        code = " ".join(t.string for t in tokens
                        if t.type not in (tokenize.COMMENT, tokenize.STRING))
        out.append((path.relative_to(PACKAGE).as_posix(), ast.parse(text), code))
    return tuple(out)


def _docstrings(tree: ast.Module) -> set[int]:
    """ids of the docstring constants of a module, its classes and functions."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                out.add(id(body[0].value))
    return out


def _assigned_names(tree: ast.Module) -> Iterator[str]:
    for node in ast.walk(tree):
        targets: list[ast.expr] = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, ast.AnnAssign):
            targets = [node.target]
        for t in targets:
            if isinstance(t, ast.Name):
                yield t.id


def _displays(tree: ast.Module) -> Iterator[list[object]]:
    """The constant elements of every tuple, list and set display, and of dict keys."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            elts = node.elts
        elif isinstance(node, ast.Dict):
            elts = [k for k in node.keys if k is not None]
        else:
            continue
        yield [e.value if isinstance(e, ast.Constant) else e for e in elts]


def _chi2(tree: ast.Module, code: str) -> bool:
    if any(n.startswith("CHI2") for n in _assigned_names(tree)):
        return True
    return any(isinstance(n, ast.Constant) and isinstance(n.value, float)
               and abs(n.value - CHI2_2DOF_95) < 1e-3 for n in ast.walk(tree))


def _horizons(tree: ast.Module, code: str) -> bool:
    return any(tuple(d) == HORIZONS_S for d in _displays(tree))


def _threshold(tree: ast.Module, code: str) -> bool:
    """THRESHOLD_M assigned, or a success threshold given as a number: a default of a
    ``threshold_m`` argument or field, or of a ``--threshold`` option."""
    if "THRESHOLD_M" in set(_assigned_names(tree)):
        return True
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            pos = a.posonlyargs + a.args
            pairs = [*zip(pos[len(pos) - len(a.defaults):], a.defaults, strict=True),
                     *zip(a.kwonlyargs, a.kw_defaults, strict=True)]
            if any(arg.arg == "threshold_m" and isinstance(d, ast.Constant)
                   for arg, d in pairs):
                return True
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if node.target.id == "threshold_m" and isinstance(node.value, ast.Constant):
                return True
        elif isinstance(node, ast.Call) and node.args and \
                isinstance(node.args[0], ast.Constant) and node.args[0].value == "--threshold":
            defaults = [k.value for k in node.keywords if k.arg == "default"]
            if any(isinstance(d, ast.Constant) for d in defaults):
                return True
    return False


def _horizon_key(tree: ast.Module, code: str) -> bool:
    return any(isinstance(n, ast.FunctionDef) and n.name == "horizon_key"
               for n in ast.walk(tree))


def _channels(tree: ast.Module, code: str) -> bool:
    return any(tuple(d) == CHANNELS for d in _displays(tree))


#: the formulas: yaw = atan2(2 (w z + x y), ...) and q = (.., sin(yaw / 2), cos(yaw / 2))
_QUATERNION = re.compile(r"atan2\s*\(\s*2(\.0)?\s*\*|\b(sin|cos)\s*\(\s*0\.5\s*\*")


def _quaternion(tree: ast.Module, code: str) -> bool:
    return bool(_QUATERNION.search(code)) or any(
        isinstance(n, ast.FunctionDef) and n.name in ("quaternion_to_yaw", "yaw_to_quaternion")
        for n in ast.walk(tree))


def _topics(tree: ast.Module, code: str) -> bool:
    """A topic name spelt out in code. Not counted: docstrings, keys of a dict whose keys
    are not all topic names (JSON fields, roles, labels), lookups by key (``d["joy"]``,
    ``d.get("joy")``) and attribute names (``setattr(obj, "joy", ...)``)."""
    names = TOPIC_NAMES | {topics.in_bag(t) for t in TOPIC_NAMES}
    skip = _docstrings(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            keys = [k for k in node.keys if isinstance(k, ast.Constant)]
            if not all(k.value in names for k in keys):
                skip |= {id(k) for k in keys}
        elif isinstance(node, ast.Subscript):
            skip.add(id(node.slice))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                node.func.attr == "get" and node.args:
            skip.add(id(node.args[0]))
        elif isinstance(node, ast.Call) and re.search(
                r"(set|get|has)attr", ast.unparse(node.func)) and len(node.args) > 1:
            skip.add(id(node.args[1]))
    return any(isinstance(n, ast.Constant) and n.value in names and id(n) not in skip
               for n in ast.walk(tree))


def _kind_list(tree: ast.Module, code: str) -> bool:
    """A list of (three or more of) the model kinds written out."""
    return any(len(KIND_NAMES & {e for e in d if isinstance(e, str)}) >= 3
               for d in _displays(tree))


#: constant -> (its one home, relative to asgp_ros/, or None for "nowhere", finder).
CONSTANTS: dict[str, tuple[str | None, Callable[[ast.Module, str], bool]]] = {
    "chi-square 2 dof 95%": ("core/metrics.py", _chi2),
    "horizons": ("core/metrics.py", _horizons),
    "success threshold": ("core/metrics.py", _threshold),
    "horizon_key": ("core/metrics.py", _horizon_key),
    "channel names": ("core/features.py", _channels),
    "quaternion <-> yaw": ("core/quaternion.py", _quaternion),
    "topic names": ("common/topics.py", _topics),
    "list of model kinds": (None, _kind_list),
}


@functools.cache
def _where(constant: str) -> list[str]:
    _home, found = CONSTANTS[constant]
    return [rel for rel, tree, code in _modules() if found(tree, code)]


@pytest.mark.parametrize("constant", sorted(CONSTANTS))
def test_each_constant_is_defined_once(constant):
    home, _found = CONSTANTS[constant]
    where = _where(constant)
    if home is not None:
        assert home in where, f"{constant}: the definition in {home} was not found"
    copies = [rel for rel in where if rel != home and rel not in PENDING.get(constant, {})]
    assert not copies, (f"{constant} is defined again in {copies}; use the one definition "
                        f"in asgp_ros/{home}" if home else f"{constant} written out in "
                        f"{copies}; read asgp_ros.core.models (the registry of kinds)")


def test_pending_copies_still_exist():
    """A pending module that now uses the one definition must leave PENDING."""
    fixed = [f"{constant}: {rel}" for constant, modules in PENDING.items()
             for rel in modules if rel not in _where(constant)]
    assert not fixed, f"no copy left, remove from PENDING in {Path(__file__).name}: {fixed}"


# -------------------------------------------------------------- YAML and README, checked
def _params(name: str) -> dict[str, object]:
    doc = yaml.safe_load((REPO / "config" / name).read_text())
    (node,) = doc.values()
    return node["ros__parameters"]


def test_yaml_topics_are_the_defined_topics():
    predictor = _params("predictor.yaml")
    assert (predictor["joy_topic"], predictor["vo_topic"], predictor["plan_topic"],
            predictor["path_topic"]) == (topics.JOY, topics.VO_TWIST, topics.JOY_PLAN,
                                         topics.PREDICTED_PATH)
    vo = _params("vo.yaml")
    assert (vo["color_topic"], vo["depth_topic"], vo["camera_info_topic"]) == (
        topics.CAMERA_COLOR, topics.CAMERA_DEPTH, topics.CAMERA_INFO)


def test_yaml_names_the_paper_horizons():
    text = (REPO / "config" / "predictor.yaml").read_text()
    assert f"the paper: {', '.join(map(horizon_key, HORIZONS_S))} s" in text
    assert _params("predictor.yaml")["horizon_s"] in HORIZONS_S


def test_readme_names_the_defined_topics_horizons_and_threshold():
    readme = (REPO / "README.md").read_text()
    table = readme[readme.index("ROS interface"):]
    table = table[:table.index("\n\n", table.index("| topic |"))]
    listed = set(re.findall(r"`([a-z_/]+)`", table))
    assert listed == TOPIC_NAMES - {topics.GROUND_TRUTH}  # ground truth: simulation only
    for bag_topic in (topics.BAG_JOY, topics.BAG_VO_TWIST):
        assert f"`{bag_topic}`" in readme
    keys = [horizon_key(h) for h in HORIZONS_S]
    assert f"--horizons {' '.join(keys)}" in readme and " / ".join(keys) in readme
    assert f"--threshold {THRESHOLD_M:.2f}" in readme
    assert f"<= {100 * THRESHOLD_M:.0f} cm" in readme


def test_readme_links_within_itself_lead_to_its_headings():
    """The contents and every other in-page link name a heading that exists (GitHub's
    anchors: lower case, punctuation dropped, spaces as hyphens)."""
    readme = (REPO / "README.md").read_text()
    headings = re.findall(r"^#{1,6} (.+)$", readme, flags=re.M)
    anchors = {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}
    links = re.findall(r"\]\(#([^)]+)\)", readme)
    assert len(links) >= len(re.findall(r"^## ", readme, flags=re.M))  # the contents
    assert sorted(set(links) - anchors) == []
