"""Writing the joints' calibration into a profile (``crtk-ctl calibrate``), keeping its comments.

ruamel.yaml round-trips YAML: comments, key order, flow style and quoting survive a load and a
dump, which PyYAML cannot do (the profiles are commented by hand). Where the calibration goes:

* the profile names a ``calibration_file``: that file (created if missing) maps joint name ->
  calibration keys; joints it does not mention keep their entry (or the profile's own keys);
* otherwise: each calibrated joint's ``calibration`` mapping in the profile itself, updated in
  place (keys this calibration does not set, and every comment, are kept).

The file is replaced atomically, and only if the result still loads as a profile.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.error import YAMLError

from .errors import ProfileError
from .profile import calibration_file_path, load_profile

_CALIBRATION_HEADER = ("Joint calibration written by `crtk-ctl calibrate` (docs/calibration.md); "
                       "the profile names\nthis file in `calibration_file`. Per joint: offset, "
                       "direction, range (ticks) as in profiles/example.yaml.\n")


def _yaml() -> YAML:
    y = YAML()  # round-trip mode
    y.preserve_quotes = True
    y.width = 4096  # never re-wrap a long flow line
    y.indent(mapping=2, sequence=4, offset=2)
    # keep `key: null` as written (ruamel's default writes an empty value)
    y.representer.add_representer(type(None), lambda r, _: r.represent_scalar("tag:yaml.org,2002:null", "null"))
    return y


def _styled(v: Any) -> Any:
    """A list as a flow sequence (``[700, 3400]``), as the profiles write ranges."""
    if isinstance(v, (list, tuple)):
        v = CommentedSeq(v)
        v.fa.set_flow_style()
    return v


def _update(target: Any, keys: dict[str, Any]) -> Any:
    """``target`` (the joint's calibration mapping, or None) with ``keys`` set, its style,
    comments and other keys kept; a new mapping is written in flow style, as the profiles do."""
    if not isinstance(target, CommentedMap):
        target = CommentedMap()
        target.fa.set_flow_style()
    for k, v in keys.items():
        target[k] = _styled(v)
    return target


def _replace(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ProfileError(f"{path}: cannot write: {exc.strerror or exc}") from exc


def write_calibration(profile_path: str | Path, calibration: dict[str, dict[str, Any]]) -> Path:
    """Write ``calibration`` (joint name -> calibration keys) where the profile keeps it (module
    docstring). Returns the file written. Blocks on file I/O. Raises ProfileError naming the file
    (unreadable, not a profile, a joint it does not have, not writable, or a result that no
    longer loads -- then nothing is changed)."""
    path = Path(profile_path)
    y = _yaml()
    try:
        data = y.load(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"{path}: cannot read profile: {exc}") from exc
    except YAMLError as exc:
        raise ProfileError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from exc
    joints = data.get("joints") if isinstance(data, dict) else None
    if not isinstance(joints, list):
        raise ProfileError(f"{path}: not a profile (no joints list)")
    by_name = {j.get("name"): j for j in joints if isinstance(j, dict)}
    unknown = sorted(set(calibration) - set(by_name))
    if unknown:
        raise ProfileError(f"{path}: no joint {unknown[0]!r} (joints: {', '.join(map(str, by_name))})")

    if data.get("calibration_file"):
        target = calibration_file_path(path, str(data["calibration_file"]))
        cal = None
        if target.exists():
            try:
                cal = y.load(target.read_text())
            except (OSError, UnicodeDecodeError, YAMLError) as exc:
                raise ProfileError(f"{target}: cannot read the calibration file: {exc}") from exc
        if not isinstance(cal, CommentedMap):
            cal = CommentedMap()
            cal.yaml_set_start_comment(_CALIBRATION_HEADER)
        for name, keys in calibration.items():
            cal[name] = _update(cal.get(name), keys)
        before = target.read_text() if target.exists() else None
        _replace(target, _dump(y, cal))
        _check(path, target, before)
        return target

    for name, keys in calibration.items():
        j = by_name[name]
        nested = j.get("backend")
        owner = nested if isinstance(nested, dict) and "calibration" in nested else j
        owner["calibration"] = _update(owner.get("calibration"), keys)
    before = path.read_text()
    _replace(path, _dump(y, data))
    _check(path, path, before)
    return path


def _dump(y: YAML, data: Any) -> str:
    buf = io.StringIO()
    y.dump(data, buf)
    return buf.getvalue()


def _check(profile: Path, written: Path, before: str | None) -> None:
    """The profile must still load; otherwise put ``written`` back as it was and raise."""
    try:
        load_profile(profile)
    except ProfileError:
        if before is None:
            written.unlink(missing_ok=True)
        else:
            _replace(written, before)
        raise
