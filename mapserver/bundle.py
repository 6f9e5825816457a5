"""What a bundle is: the manifest model, the completeness check, and safe paths inside it.

A bundle is one directory ``inbox/<bundle_id>/`` holding ``bundle.yaml`` and the map files it
names (contract section 2).
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    ValidationError,
    field_validator,
    model_validator,
)

from mapserver.config import LimitsConfig
from mapserver.errors import (
    BundleError,
    BundleIncomplete,
    ChecksumMismatch,
    FileNotThere,
    ManifestNotYaml,
    describe_validation,
    no_such_path,
)
from mapserver.geometry import MAX_COORDINATE_M, Pose2D, Transform2D, yaw_from_quaternion
from mapserver.maps import MAX_MAP_YAML_BYTES

MANIFEST = "bundle.yaml"
# libyaml's loader when PyYAML was built with it: a manifest with a long trajectory parses
# about ten times faster. Same safe subset of YAML either way.
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_LIMITS = LimitsConfig()
BUNDLE_ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


def is_valid_bundle_id(name: str) -> bool:
    return BUNDLE_ID_RE.fullmatch(name) is not None


UPLOAD_TO = "mapserver-inbox:"
"""The rsync destination a robot uploads to (README, "Deploying"): an ssh ``Host`` whose key
the server restricts to writing into the inbox (rrsync), so a path is relative to the inbox."""


def upload_commands(bundle_dir: str, destination: str = UPLOAD_TO) -> list[list[str]]:
    """The two rsync calls that upload bundle folder ``bundle_dir`` to the inbox at
    ``destination`` (README, "Deploying"): first the maps, group-writable (the daemon moves the
    folder) with rsync's partial files under a dot-name (never read), then ``bundle.yaml``
    alone, last: when it arrives, the upload is complete."""
    source = bundle_dir.rstrip("/") or "/"
    bundle_id = Path(source).name
    if bundle_id in ("", ".", ".."):  # `-o .`: the folder's own name, not the inbox's root
        bundle_id = Path(source).resolve().name
    sep = "" if destination.endswith((":", "/")) else "/"
    target = f"{destination}{sep}{bundle_id}/"
    common = ["rsync", "-a", "--chmod=D2770,F660"]
    return [
        [*common, "--partial-dir=.rsync-partial", f"--exclude={MANIFEST}", f"{source}/", target],
        [*common, f"{source}/{MANIFEST}", target],
    ]


def is_in_flight(name: str) -> bool:
    """Names of files still being uploaded (rsync temp names, editor backups): never read."""
    return name.startswith(".") or name.endswith((".tmp", ".part", "~"))


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Quaternion(_Model):
    x: float
    y: float
    z: float
    w: float


class PoseModel(_Model):
    """A pose with ``yaw`` or a ROS ``orientation`` quaternion (exactly one of them)."""

    x: float
    y: float
    yaw: float | None = None
    orientation: Quaternion | None = None

    @model_validator(mode="after")
    def _one_heading(self) -> PoseModel:
        if (self.yaw is None) == (self.orientation is None):
            raise ValueError("give exactly one of 'yaw' and 'orientation'")
        values = [self.x, self.y, self.yaw if self.yaw is not None else 0.0]
        if self.orientation is not None:
            o = self.orientation
            values += [o.x, o.y, o.z, o.w]
        if not all(math.isfinite(v) for v in values):
            raise ValueError("pose values must be finite numbers (no NaN or inf)")
        if max(abs(self.x), abs(self.y)) > MAX_COORDINATE_M:
            raise ValueError(
                f"pose x and y must lie within {MAX_COORDINATE_M:.0e} m of the frame's origin, "
                f"got ({self.x:g}, {self.y:g})"
            )
        return self

    def to_pose(self) -> Pose2D:
        if self.orientation is not None:
            o = self.orientation
            try:
                yaw = yaw_from_quaternion(o.x, o.y, o.z, o.w)
            except ValueError as error:
                raise BundleError(str(error), file=MANIFEST) from None
        else:
            assert self.yaw is not None
            yaw = self.yaw
        return Pose2D(self.x, self.y, yaw)


class PosePair(_Model):
    nav2: PoseModel
    slam: PoseModel


FileName = Annotated[str, StringConstraints(min_length=1)]


class Manifest(_Model):
    """``bundle.yaml`` (contract section 2)."""

    format: int = Field(1)
    robot: Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9._-]+$")]
    stamp: str
    slam_map: FileName
    nav2_map: FileName | None = None
    pose: PosePair
    trajectory: list[PoseModel] | None = None
    checksums: dict[str, Annotated[str, StringConstraints(pattern=r"^[0-9a-fA-F]{64}$")]] | None = (
        None
    )

    @field_validator("format")
    @classmethod
    def _format_one(cls, value: int) -> int:
        if value != 1:
            raise ValueError(f"unsupported format {value}; this server reads format 1")
        return value

    @field_validator("stamp", mode="before")
    @classmethod
    def _stamp_text(cls, value: object) -> object:
        # YAML turns an unquoted ISO time into a datetime; keep the text form.
        if hasattr(value, "isoformat"):
            return value.isoformat().replace("+00:00", "Z")
        return value

    @field_validator("stamp")
    @classmethod
    def _stamp_iso(cls, value: str) -> str:
        try:
            parsed = datetime.fromisoformat(value.replace("Z", "+00:00"))
        except ValueError:
            raise ValueError(
                f"{value!r} is not an ISO 8601 time (write it like 2026-11-21T10:15:00Z)"
            ) from None
        if parsed.tzinfo is None:
            raise ValueError(f"{value!r} has no time zone (write it like 2026-11-21T10:15:00Z)")
        try:
            parsed.astimezone(timezone.utc).timestamp()
        except (OverflowError, ValueError):
            # 0001-01-01T00:30:00+01:00 is a valid text whose UTC time is before year 1.
            raise ValueError(f"{value!r} lies outside the years 1-9999 in UTC") from None
        return value

    def nav2_from_slam_prior(self) -> Transform2D:
        """The transform slam -> nav2 given by the pose pair (contract section 1)."""
        return Transform2D.from_poses(self.pose.nav2.to_pose(), self.pose.slam.to_pose())

    def trajectory_poses(self) -> list[Pose2D]:
        return [p.to_pose() for p in self.trajectory or []]


# How YAML reads a scalar it was given no tag for: the quick check cuts out a key's value only
# when the key is read as a string (not ``yes``, ``1``, the merge key ``<<``).
_RESOLVER = yaml.resolver.Resolver()
_STR_TAG = "tag:yaml.org,2002:str"


@dataclass(frozen=True)
class _Cut:
    """A manifest's text with the values of its top-level ``trajectory`` and of the keys the
    model does not know replaced by null: how many poses that trajectory held, and which
    unknown keys were cut."""

    text: str
    poses: int
    unknown: tuple[str, ...]


def _cut_for_check(text: str) -> _Cut | None:
    """``text`` (a manifest) with the values of its top-level ``trajectory`` and of every
    top-level key the model does not know (a string) replaced by null; None when there is
    nothing to cut, the trajectory is given twice or holds no sequence, or its YAML cannot be
    read (the full parse says why).

    Found from the parser's events, which libyaml makes ten times faster than the objects of a
    full load (100,000 poses: 0.5 s against 4.4 s on 2 cores); their marks index characters of
    ``text``."""
    depth = 0  # collections open
    top = 0  # nodes seen directly in the top-level mapping: keys, then values
    key: str | None = None
    cuts: list[tuple[int, int]] = []
    open_from: int | None = None  # inside a value being cut: where it starts
    counting = False  # that value is the trajectory: count its items
    unknown: list[str] = []
    keys = poses = 0
    try:
        for event in yaml.parse(text, Loader=_LOADER):
            if isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
                if open_from is not None and depth == 1:
                    assert event.end_mark is not None
                    cuts.append((open_from, event.end_mark.index))
                    open_from, counting = None, False
                continue
            if not isinstance(event, yaml.NodeEvent):
                continue  # the stream's and the documents' own events
            if depth == 0 and not isinstance(event, yaml.MappingStartEvent):
                return None  # not a mapping: the full parse says so
            if depth == 1:
                if top % 2 == 0:
                    key = _string_key(event)
                    keys += key == "trajectory"
                elif key == "trajectory":
                    if not isinstance(event, yaml.SequenceStartEvent):
                        return None  # null, a number, a mapping: the full parse judges it
                    assert event.start_mark is not None
                    open_from, counting = event.start_mark.index, True
                elif isinstance(key, str) and key not in Manifest.model_fields:
                    unknown.append(key)
                    assert event.start_mark is not None and event.end_mark is not None
                    if isinstance(event, yaml.CollectionStartEvent):
                        open_from = event.start_mark.index
                    else:  # a scalar or an alias: cut where it stands
                        cuts.append((event.start_mark.index, event.end_mark.index))
                top += 1
            elif depth == 2 and counting:
                poses += 1  # an item of the trajectory
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
    except yaml.YAMLError:
        return None
    if keys > 1 or not cuts:
        return None  # the trajectory twice (YAML keeps the last), or nothing to cut
    # Each on a line of its own: a block collection ends where the next key starts.
    pieces, at = [], 0
    for start, end in cuts:
        pieces += [text[at:start], " null\n"]
        at = end
    pieces.append(text[at:])
    return _Cut("".join(pieces), poses, tuple(unknown))


def _string_key(event: yaml.Event) -> str | None:
    """A top-level key's name when YAML reads it as a string (plain or quoted, or tagged so);
    None for any other key (a number, a bool, a collection)."""
    if not isinstance(event, yaml.ScalarEvent):
        return None
    tag = event.tag
    if tag in (None, "!"):
        tag = _RESOLVER.resolve(yaml.ScalarNode, event.value, event.implicit)  # type: ignore[no-untyped-call]
    return event.value if tag == _STR_TAG else None


def parse_manifest(
    text: str,
    *,
    source: str | Path = MANIFEST,
    limits: LimitsConfig = _LIMITS,
    trajectory: bool = True,
) -> Manifest:
    """Parse and validate the text of ``bundle.yaml``; errors name the field. A trajectory
    longer than ``limits.max_trajectory_poses`` is refused before its poses are validated.

    ``trajectory=False``: its poses are counted, not read (the manifest returned has none), and
    the values of keys the model does not know are not read either (the manifest is refused
    for them, naming them, as the whole parse does): what the daemon's main loop checks of an
    upload, where a trajectory of 100,000 poses took 4-8 s to load, and 16 MiB under an unknown
    key 12 s (1.5 s cut); the worker reads the whole manifest. A cut text YAML cannot read (an
    alias into what was cut) gets the whole parse, and its reason."""
    if not trajectory:
        cut = _cut_for_check(text)
        if cut is not None:
            _refuse_long_trajectory(cut.poses, source, limits)
            data = _load(cut.text, source, fallback=True)
            if data is not None:
                try:
                    return _validated(data, source, limits)
                except BundleError:
                    if cut.unknown:
                        raise  # refused for keys no full parse would accept either
                    # Otherwise the whole text's parse names the problem where it lies.
    data = _load(text, source)
    return _validated(data, source, limits)


def _load(text: str, source: str | Path, *, fallback: bool = False) -> object:
    """The YAML document of ``text``; a :class:`BundleError` naming the problem when it cannot
    be read (None instead with ``fallback``)."""
    try:
        return yaml.load(text, Loader=_LOADER)
    except (yaml.YAMLError, ValueError, TypeError) as error:  # `!!float abc`: a ValueError
        if fallback:
            return None
        problem = " ".join(str(error).split())
        raise ManifestNotYaml(f"not valid YAML: {problem}", file=source) from None


def _validated(data: object, source: str | Path, limits: LimitsConfig) -> Manifest:
    """The manifest of a loaded document, or a :class:`BundleError` that names the field."""
    if not isinstance(data, dict):
        raise BundleError("the manifest must be a mapping of keys to values", file=source)
    poses = data.get("trajectory")
    if isinstance(poses, list):
        _refuse_long_trajectory(len(poses), source, limits)
    try:
        return Manifest.model_validate(data)
    except ValidationError as error:
        raise BundleError(describe_validation(error), file=source) from None


def _refuse_long_trajectory(poses: int, source: str | Path, limits: LimitsConfig) -> None:
    if poses > limits.max_trajectory_poses:
        raise BundleError(
            f"the trajectory has {poses} poses, more than limits.max_trajectory_poses "
            f"{limits.max_trajectory_poses}: send fewer (one pose every 10-20 cm is plenty)",
            file=source,
        )


def read_manifest(
    bundle_dir: Path, *, limits: LimitsConfig = _LIMITS, trajectory: bool = True
) -> Manifest:
    """Read and parse ``bundle.yaml``; one larger than ``limits.max_manifest_bytes`` is refused
    before it is read. ``trajectory=False``: its poses counted, not read
    (:func:`parse_manifest`)."""
    path = bundle_dir / MANIFEST
    try:
        size = path.stat().st_size
        if size > limits.max_manifest_bytes:
            raise BundleError(
                f"the manifest is {size} bytes, more than limits.max_manifest_bytes "
                f"{limits.max_manifest_bytes}",
                file=path,
            )
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BundleIncomplete("no bundle.yaml yet", file=path) from None
    except (OSError, UnicodeDecodeError) as error:
        raise BundleError(f"cannot read the manifest: {error}", file=path) from None
    return parse_manifest(text, source=path, limits=limits, trajectory=trajectory)


def check_bundle_dir(path: Path) -> None:
    """That ``path`` is a bundle folder, before anything in it is read; a :class:`BundleError`
    that says what it is instead: a path that does not exist (with the names close to it), a
    file (the manifest itself, say), a folder without ``bundle.yaml`` (one holding bundle
    folders, say)."""
    path = Path(path)
    if not path.exists():
        raise BundleError(no_such_path(path), file=path)
    if not path.is_dir():
        if path.name == MANIFEST:
            hint = f"give the folder that holds it: {path.parent}"
        else:
            hint = "a bundle is the folder that holds bundle.yaml and the maps"
        raise BundleError(f"a file, not a bundle folder; {hint}", file=path)
    if not (path / MANIFEST).exists():
        raise BundleError(
            f"not a bundle: no bundle.yaml in it{nested_bundles_hint(path)}", file=path
        )


def nested_bundles_hint(path: Path) -> str:
    """When folder ``path`` holds bundle folders (a folder of bundles given, or uploaded, as one
    bundle), a hint that names a few."""
    try:
        inner = sorted(p.name for p in path.iterdir() if (p / MANIFEST).is_file())
    except OSError:
        return ""
    if not inner:
        return ""
    shown = ", ".join(inner[:3]) + (", ..." if len(inner) > 3 else "")
    return f"; it holds {len(inner)} bundle folder{'s' if len(inner) > 1 else ''} ({shown})"


def safe_member(bundle_dir: Path, name: str, *, what: str, source: Path) -> Path:
    """The path of file ``name`` inside ``bundle_dir``; a name that leaves the bundle (absolute,
    ``..``, or a symlink pointing outside) is a :class:`BundleError`."""
    if not name or Path(name).is_absolute():
        raise BundleError(f"{what} '{name}' must be a relative path inside the bundle", file=source)
    root = bundle_dir.resolve()
    candidate = bundle_dir / name
    try:
        resolved = candidate.resolve()
    except (RuntimeError, OSError) as error:  # a symlink loop: RuntimeError before Python 3.13
        problem = (
            "is a symlink loop" if "loop" in str(error).lower() else f"cannot be resolved ({error})"
        )
        raise BundleError(f"{what} '{name}' {problem}", file=source) from None
    if not resolved.is_relative_to(root):
        raise BundleError(f"{what} '{name}' points outside the bundle", file=source)
    return candidate


def map_image_name(map_yaml: Path) -> str:
    """The ``image:`` entry of a map YAML, read without loading the image (for completeness)."""
    try:
        size = map_yaml.stat().st_size
        if size > MAX_MAP_YAML_BYTES:
            raise BundleError(
                f"map YAML is {size} bytes, larger than {MAX_MAP_YAML_BYTES}: is it a map YAML?",
                file=map_yaml,
            )
        data = yaml.load(map_yaml.read_text(encoding="utf-8"), Loader=_LOADER)
    except FileNotFoundError:
        raise BundleIncomplete("missing", file=map_yaml) from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        problem = " ".join(str(error).split())
        raise BundleError(f"not a readable map YAML: {problem}", file=map_yaml) from None
    if not isinstance(data, dict) or not isinstance(data.get("image"), str):
        raise BundleError("map YAML has no 'image:' entry", file=map_yaml)
    return str(data["image"])


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class BundleFiles:
    """The files of a complete bundle: the manifest and every file it depends on."""

    manifest: Manifest
    slam_yaml: Path
    slam_image: Path
    nav2_yaml: Path | None
    nav2_image: Path | None

    def paths(self) -> list[Path]:
        out = [self.slam_yaml, self.slam_image]
        out += [p for p in (self.nav2_yaml, self.nav2_image) if p is not None]
        return out


def check_bundle_files(
    bundle_dir: Path,
    *,
    verify_checksums: bool = True,
    limits: LimitsConfig = _LIMITS,
    trajectory: bool = True,
) -> BundleFiles:
    """Check that the manifest parses, every file it names is present and every listed checksum
    matches (with ``verify_checksums=False``: that every checksummed file is present, for a
    bundle whose checksums were verified already).

    Raises :class:`BundleIncomplete` while a file is missing or a checksum does not match (the
    upload may still be going on) and :class:`BundleError` for a bundle that can never be right.
    The settle time (nothing changed for a while) is the caller's business.
    ``trajectory=False``: the trajectory's poses are counted, not read (:func:`parse_manifest`).
    """
    manifest = read_manifest(bundle_dir, limits=limits, trajectory=trajectory)
    source = bundle_dir / MANIFEST
    yamls: dict[str, Path | None] = {"slam": None, "nav2": None}
    images: dict[str, Path | None] = {"slam": None, "nav2": None}
    for key, name in (("slam", manifest.slam_map), ("nav2", manifest.nav2_map)):
        if name is None:
            continue
        yaml_path = safe_member(bundle_dir, name, what=f"{key}_map", source=source)
        if not yaml_path.is_file():
            raise FileNotThere(f"{key}_map '{name}'", file=source)
        image_name = map_image_name(yaml_path)
        image_rel = (
            str(Path(name).parent / image_name)
            if not Path(image_name).is_absolute()
            else image_name
        )
        image_path = safe_member(bundle_dir, image_rel, what="map image", source=yaml_path)
        if not image_path.is_file():
            raise FileNotThere(f"map image '{image_name}'", file=yaml_path)
        yamls[key], images[key] = yaml_path, image_path
    checksummed = []
    for name, expected in (manifest.checksums or {}).items():
        path = safe_member(bundle_dir, name, what="checksummed file", source=source)
        if not path.is_file():
            raise FileNotThere(f"checksummed file '{name}'", file=source)
        checksummed.append((name, expected.lower(), path))
    # Hashed once every file is there: a ChecksumMismatch means a bundle with nothing missing.
    for name, expected, path in checksummed if verify_checksums else []:
        try:
            actual = sha256_file(path)
        except FileNotFoundError:
            raise FileNotThere(f"checksummed file '{name}'", file=source) from None
        except PermissionError as error:
            raise BundleError(
                f"checksummed file '{name}' cannot be read: {error.strerror}", file=path
            ) from None
        if actual != expected:
            raise ChecksumMismatch(name, expected=expected, actual=actual, file=path)
    slam_yaml, slam_image = yamls["slam"], images["slam"]
    assert slam_yaml is not None and slam_image is not None
    return BundleFiles(manifest, slam_yaml, slam_image, yamls["nav2"], images["nav2"])
