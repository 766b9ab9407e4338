"""Reading arm configs from disk: YAML (DH table or a URDF reference) and URDF files.

``load_arm("wmra")`` finds the shipped ``config/wmra.yaml`` (package data wherever
armfusion is installed: :mod:`armfusion.fusion.shipped`); any other argument is a path.
Validation itself is :func:`armfusion.models.arm_config.build_arm`.
"""

from __future__ import annotations

import stat
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from armfusion.fusion.shipped import shipped_config_dir
from armfusion.models.arm import ArmModel, Joint
from armfusion.models.arm_config import ConfigError, ConfigProblem, build_arm
from armfusion.sensors.samples import clipped_repr

MAX_CONFIG_BYTES = 4_000_000
"""A config file larger than this is refused unread (the shipped ones are 2-4 kB; a
calibrated one with its covariances some tens of kB)."""

MAX_YAML_VALUES = 200_000
"""Values a YAML file may hold once its aliases are expanded: a 300-byte "alias bomb"
(nine anchors each repeating the one before ten times) means 10^9 of them."""


MAX_NUMBER_CHARS = 64
"""An integer of a config in more characters than this is refused (a float needs at most 24;
the largest a config holds, 2^32 counts per revolution, ten), as the recording CSV's cells."""


def _yaml_problem(source: str, where: str, message: str) -> ConfigError:
    return ConfigError([ConfigProblem(source, where, None, message)])


def _expanded_size(node: yaml.Node, source: str) -> int:
    """How many values ``node`` holds with every alias expanded, counted without
    expanding (each node once, by identity); refuses past :data:`MAX_YAML_VALUES` and
    a node that contains itself."""
    sizes: dict[int, int] = {}
    open_nodes: set[int] = set()

    def size(n: yaml.Node) -> int:
        key = id(n)
        if key in sizes:
            return sizes[key]
        if key in open_nodes:
            raise _yaml_problem(source, f"line {n.start_mark.line + 1}",
                                "a YAML alias refers to a node that contains it (a recursive alias)")
        open_nodes.add(key)
        total = 1
        if (isinstance(n, yaml.ScalarNode) and n.tag == "tag:yaml.org,2002:int"
                and len(n.value) > MAX_NUMBER_CHARS):  # (Python's int() stops at 4300 digits: a traceback)
            raise _yaml_problem(source, f"line {n.start_mark.line + 1}",
                                f"a number of {len(n.value)} characters (it starts {n.value[:16]!r}); "
                                "no number needs so many")
        if isinstance(n, yaml.SequenceNode):
            total += sum(size(c) for c in n.value)
        elif isinstance(n, yaml.MappingNode):
            _refuse_repeated_keys(n, source)
            total += sum(size(k) + size(v) for k, v in n.value)
        open_nodes.discard(key)
        sizes[key] = total
        if total > MAX_YAML_VALUES:
            raise _yaml_problem(
                source, f"line {n.start_mark.line + 1}",
                f"its aliases expand to more than {MAX_YAML_VALUES} values (a YAML alias bomb?); "
                "a config is far smaller")
        return total

    return size(node)


def _refuse_repeated_keys(n: yaml.MappingNode, source: str) -> None:
    """A mapping that gives one key twice (YAML keeps the last, silently) is refused, naming
    the key and both lines."""
    first: dict[str, int] = {}
    for k, _ in n.value:
        if not isinstance(k, yaml.ScalarNode) or k.tag == "tag:yaml.org,2002:merge":
            continue
        line = k.start_mark.line + 1
        if k.value in first:
            raise _yaml_problem(source, f"line {line}",
                                f"the key {clipped_repr(k.value)} is given twice (first on line "
                                f"{first[k.value]}); a config gives each key once")
        first[k.value] = line


def read_bounded(path: Path, limit: int, what: str) -> bytes:
    """The bytes of the regular file ``path``, refused (``ValueError``, one line) when it is
    not a regular file (a device such as /dev/zero, a FIFO that would block) or holds more
    than ``limit`` bytes; never reads more than ``limit + 1``."""
    # (a NUL is refused by the callers once the text is decoded: random bytes are "not
    # UTF-8" first)
    st = path.stat()
    if not stat.S_ISREG(st.st_mode):
        raise ValueError("not a regular file (a device, a FIFO, a directory)")
    if st.st_size > limit:
        raise ValueError(f"{st.st_size} bytes is more than {what} may be ({limit})")
    with open(path, "rb") as f:
        raw = f.read(limit + 1)
    if len(raw) > limit:
        raise ValueError(f"more than {limit} bytes is more than {what} may be")
    return raw


def read_yaml(path: Path) -> Any:
    """A YAML file's data, read safely and within bounds, or :class:`ConfigError` with a
    one-line reason: not a regular file of at most :data:`MAX_CONFIG_BYTES` (read no
    further: ``/dev/zero`` is refused at once), a NUL byte, not UTF-8 text, not YAML, a key
    given twice in one mapping, nested too deeply, or aliases that expand past
    :data:`MAX_YAML_VALUES`. Only
    plain data is built (``yaml.SafeLoader``: no Python objects)."""
    source = str(path)
    try:
        raw = read_bounded(path, MAX_CONFIG_BYTES, "a config")
    except OSError as e:
        raise _yaml_problem(source, "(file)", f"cannot read it: {e.strerror or e}") from None
    except ValueError as e:
        raise _yaml_problem(source, "(file)", f"{e}; is it a config?") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise _yaml_problem(source, f"byte {e.start}",
                            "not UTF-8 text; a config is a YAML text file") from None
    if "\0" in text:
        line = text[: text.index("\0")].count("\n") + 1
        raise _yaml_problem(source, f"line {line}", "holds a NUL byte; a config is a YAML text file")
    try:
        loader = yaml.SafeLoader(text)
    except yaml.YAMLError as e:  # (a character YAML does not take, met as the reader starts)
        raise _yaml_problem(source, "(file)", f"not valid YAML: {clipped_repr(str(e), 80)[1:-1]}") from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _expanded_size(node, source)
        return loader.construct_document(node)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "(file)"
        what = getattr(e, "problem", None) or type(e).__name__
        raise _yaml_problem(source, where, f"not valid YAML: {clipped_repr(what, 80)[1:-1]}") from None
    except RecursionError:
        raise _yaml_problem(source, "(file)", "nested too deeply to be a config") from None
    finally:
        loader.dispose()


def resolve_config_path(name_or_path: str | Path) -> Path:
    """A path as given if it exists, else a shipped config by name (``wmra`` or
    ``wmra.yaml``), else one in ``./config/`` by name."""
    p = Path(name_or_path)
    if p.exists():
        return p
    shipped_dir = shipped_config_dir()
    for base in (shipped_dir, Path.cwd() / "config"):
        for cand in (base / f"{name_or_path}.yaml", base / str(name_or_path)):
            if cand.exists():
                return cand
    shipped = sorted(x.stem for x in shipped_dir.glob("*.yaml")) if shipped_dir.is_dir() else []
    raise FileNotFoundError(
        f"no arm config {str(name_or_path)!r}: not a file, and not one of the shipped configs "
        f"{shipped}"
    )


def load_arm(name_or_path: str | Path) -> ArmModel:
    """Load and validate an arm config (YAML, or a bare URDF), raising :class:`ConfigError`."""
    path = resolve_config_path(name_or_path)
    source = str(path)
    if path.suffix.lower() == ".urdf":
        raise ConfigError([ConfigProblem(
            source, "(file)", path.name,
            "a URDF holds the kinematics only; reference it from a YAML config "
            "(arm.urdf: file.urdf) that adds joint limits, encoder counts and sensors")])
    data = read_yaml(path)
    urdf_joints = None
    if (isinstance(data, dict) and isinstance(data.get("arm"), dict)
            and isinstance(data["arm"].get("urdf"), str) and data["arm"]["urdf"]):
        urdf_path = (path.parent / data["arm"]["urdf"]).resolve()
        try:
            urdf_joints = joints_from_urdf(urdf_path)
        except (OSError, ValueError) as e:
            raise ConfigError([ConfigProblem(source, "arm.urdf", data["arm"]["urdf"], str(e))]) from e
    arm = build_arm(data, source, urdf_joints)
    # the effects too, now: a bad one found later would be blamed on the recording
    from armfusion.models.effects import model_problems

    _, problems = model_problems(arm, arm.effects, source, "effects")
    if problems:
        raise ConfigError(problems)
    return arm


def _check_urdf_text(path: Path) -> None:
    """Refuse, in one line naming the file, a URDF that is not a regular file of at most
    :data:`MAX_CONFIG_BYTES`, holds a NUL, is not UTF-8, declares a DOCTYPE or an entity (a
    URDF needs neither; an entity can expand a few bytes to gigabytes), or is not XML."""
    import xml.etree.ElementTree as ET

    try:
        text = read_bounded(path, MAX_CONFIG_BYTES, "a URDF").decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"URDF {path.name}: byte {e.start} is not UTF-8; a URDF is XML text") from None
    except ValueError as e:
        raise ValueError(f"URDF {path.name}: {e}") from None
    if "\0" in text:
        line = text[: text.index("\0")].count("\n") + 1
        raise ValueError(f"URDF {path.name}: line {line} holds a NUL byte; a URDF is XML text")
    upper = text.upper()
    for decl in ("<!DOCTYPE", "<!ENTITY"):
        if decl in upper:
            line = text[: upper.index(decl)].count("\n") + 1
            raise ValueError(f"URDF {path.name}: line {line}: a {decl[2:]} declaration; a URDF needs none, "
                             "and it is refused (an entity can expand to gigabytes)")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise ValueError(f"URDF {path.name}: not XML ({e})") from None
    for joint in root.iter("joint"):  # (the URDF parser's own words were numpy's broadcasting)
        for tag, attr in (("origin", "xyz"), ("origin", "rpy"), ("axis", "xyz")):
            for el in joint.iter(tag):
                value = el.get(attr)
                if value is not None and not _three_numbers(value):
                    raise ValueError(f"URDF {path.name}: joint {clipped_repr(joint.get('name', '?'))}: "
                                     f"{tag} {attr}={clipped_repr(value)} is not three numbers")


def _three_numbers(text: str) -> bool:
    try:
        return len([float(x) for x in text.split()]) == 3
    except ValueError:
        return False


def read_yaml_of(path: Path, what: str) -> Any:
    """:func:`read_yaml` for a YAML file that is not an arm config (``what``: ``maneuver file``):
    its refusal a ``ValueError`` headed ``what`` and the path (its end kept whole), not "arm
    config"."""
    try:
        return read_yaml(path)
    except ConfigError as e:
        where = str(path) if len(str(path)) <= 80 else "…" + str(path)[-79:]
        said = "; ".join(f"{q.key}: {q.message}" for q in e.problems)
        raise ValueError(f"{what} {where}: {said}") from None


def _check_urdf_origin(path: Path, joint: str, origin: np.ndarray) -> None:
    """A joint's origin: finite, and its offset below 100 m (the configs' length bound)."""
    from armfusion.models.arm_config import MAX_LENGTH_MM

    if not np.all(np.isfinite(origin)):
        raise ValueError(f"URDF {path.name}: joint {joint!r}: its origin is not finite (xyz, rpy)")
    far_m = float(np.abs(origin[:3, 3]).max())  # (a norm of 1e308s overflows)
    if not far_m < MAX_LENGTH_MM / 1000.0:
        raise ValueError(f"URDF {path.name}: joint {joint!r}: its origin is {far_m:.3g} m away along an "
                         f"axis; a length is below {MAX_LENGTH_MM / 1000:g} m")


def joints_from_urdf(path: Path) -> tuple[Joint, ...]:
    """The revolute/continuous joints of a URDF's serial chain, base to tip.

    Fixed joints between them are folded into the next joint's pre-transform (or the
    last joint's post-transform). Limits and encoder counts come from the YAML config.
    """
    import yourdfpy

    if not Path(path).exists():
        raise ValueError(f"URDF file not found: {path}")
    _check_urdf_text(path)
    try:
        robot = yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False)
    except Exception as e:  # (yourdfpy's own errors have no common base): one line, named
        why = clipped_repr(f"{type(e).__name__}: {e}", 100)[1:-1]
        raise ValueError(f"URDF {path.name}: not a URDF ({why})") from None
    children: dict[str, list] = {}
    child_links = set()
    for j in robot.robot.joints:
        children.setdefault(j.parent, []).append(j)
        child_links.add(j.child)
    roots = [link.name for link in robot.robot.links if link.name not in child_links]
    if len(roots) != 1:
        raise ValueError(f"URDF {path.name}: expected one root link, found {roots}")
    out: list[Joint] = []
    T_acc = np.eye(4)
    link = roots[0]
    while link in children:
        kids = children[link]
        if len(kids) != 1:
            raise ValueError(
                f"URDF {path.name}: link {link!r} has {len(kids)} child joints; "
                "armfusion needs a serial chain"
            )
        j = kids[0]
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=float)
        _check_urdf_origin(path, j.name, origin)
        T_acc = T_acc @ origin
        if j.type in ("revolute", "continuous"):
            axis = np.asarray(j.axis if j.axis is not None else [1.0, 0.0, 0.0], dtype=float)
            with np.errstate(over="ignore"):  # (a length of 1e308s overflows: no direction then)
                length = float(np.linalg.norm(axis)) if np.all(np.isfinite(axis)) else np.nan
            if not 1e-9 < length < np.inf:
                raise ValueError(f"URDF {path.name}: joint {j.name!r}: axis {clipped_repr(axis.tolist())} "
                                 "is not a direction (finite, not zero)")
            axis = axis / length
            out.append(Joint(
                name=j.name, R_pre=T_acc[:3, :3].copy(), p_pre_m=T_acc[:3, 3].copy(), axis=axis,
                R_post=np.eye(3), p_post_m=np.zeros(3), offset_rad=0.0,
                min_rad=-np.pi, max_rad=np.pi, counts_per_rev=1.0,
            ))
            T_acc = np.eye(4)
        elif j.type != "fixed":
            raise ValueError(f"URDF {path.name}: joint {j.name!r} is {j.type}; only revolute, "
                             "continuous and fixed joints are supported")
        link = j.child
    if not out:
        raise ValueError(f"URDF {path.name}: no revolute joint found")
    if not np.allclose(T_acc, np.eye(4)):
        last = out[-1]
        out[-1] = Joint(**{**last.__dict__, "R_post": T_acc[:3, :3].copy(),
                           "p_post_m": T_acc[:3, 3].copy()})
    return tuple(out)
