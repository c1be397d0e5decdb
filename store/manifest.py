"""The dataset manifest: ``manifest.json`` beside the shards, its hashing and verification.

The manifest lists every finished shard (relative path, scene seed, frame range, rates, sha256,
byte size) in dataset order and the full dataset config; ``"complete": true`` once every shard
is in. It is rewritten atomically (temporary file + rename). The generator (:mod:`rainbench.gen`)
writes it; every reader finds a dataset's shards through :func:`list_shards`.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path, PurePosixPath

import numpy as np

from .rates import check_rate_list
from .shard import ShardFormatError, open_checked, read_rgb, shard_name

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "rainbench.manifest"
MANIFEST_VERSION = 1
SHARD_GLOB = "scene*_f*.h5"
"""File names of shards (:func:`rainbench.store.shard.shard_name`)."""
_SHA256 = re.compile(r"[0-9a-f]{64}")


class DatasetError(ValueError):
    """A dataset request or directory that cannot be honoured; the message is one line."""


def is_int(value) -> bool:
    """Whether ``value`` is an integer (``bool`` is not one): the check of every integer field
    of a manifest and of the generator's configs."""
    return isinstance(value, int) and not isinstance(value, bool)


def sha256_of(path: Path) -> str:
    """Hex SHA-256 of the file ``path``. ``hashlib.file_digest`` reads into one reused buffer:
    the paper clip's 1.7 GB shard in 1.41 s against 1.64-1.86 s for 4 MB reads."""
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()


def shard_entry(path: Path, root: Path, *, scene_seed: int, frame_offset: int, frames: int,
                rates) -> dict:
    """The manifest entry of the finished shard ``path`` of dataset ``root`` (hashes the file)."""
    return {
        "path": path.relative_to(root).as_posix(),
        "scene_seed": scene_seed,
        "frame_offset": frame_offset,
        "frames": frames,
        "rates": [float(rate) for rate in rates],
        "sha256": sha256_of(path),
        "bytes": path.stat().st_size,
    }


def _atomic_write_json(path: Path, payload: dict) -> None:
    """Write ``path`` through a temporary file renamed over it; an OSError (a full disk) removes
    the temporary file and is a :class:`DatasetError` naming ``path``."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "w") as handle:
            json.dump(payload, handle, indent=1, sort_keys=True)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except OSError as error:
        tmp.unlink(missing_ok=True)
        raise DatasetError(f"{path}: cannot write it ({error.strerror or error})") from None


def write_manifest(root: Path, config: dict, entries: list[dict], complete: bool) -> Path:
    """Write ``root/manifest.json`` atomically: the dataset ``config`` (its JSON dict), the
    finished shards' ``entries`` in dataset order and whether every shard is in."""
    path = root / MANIFEST
    _atomic_write_json(path, {
        "format": MANIFEST_FORMAT, "format_version": MANIFEST_VERSION,
        "config": config, "complete": complete, "shards": entries,
    })
    return path


def read_manifest(root: str | Path) -> dict | None:
    """The manifest of dataset ``root`` (None if it has none); errors name the file."""
    path = Path(root) / MANIFEST
    if not path.exists():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as error:  # UnicodeDecodeError and JSONDecodeError included
        raise DatasetError(f"{path}: not a readable manifest ({error})") from error
    except RecursionError:
        raise DatasetError(f"{path}: not a readable manifest (nested too deeply)") from None
    return check_manifest(manifest, path)


def unfinished_count(manifest: dict | None) -> int | None:
    """How many finished shards ``manifest`` (:func:`read_manifest`'s) lists when it says the
    dataset is incomplete (an interrupted or still running ``rainbench generate``); None for a
    complete dataset or no manifest."""
    if manifest is None or manifest["complete"]:
        return None
    return len(manifest["shards"])


def _show(value) -> str:
    text = repr(value) if not isinstance(value, (dict, list)) else type(value).__name__
    return text if len(text) <= 60 else text[:57] + "..."


_ENTRY_FIELDS = (
    ("path", lambda v: isinstance(v, str) and v != "", "a non-empty relative path"),
    ("scene_seed", lambda v: is_int(v) and v >= 0, "an integer >= 0"),
    ("frame_offset", lambda v: is_int(v) and v >= 0, "an integer >= 0"),
    ("frames", lambda v: is_int(v) and v >= 1, "an integer >= 1"),
    ("rates", lambda v: isinstance(v, list) and len(v) > 0 and all(
        isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) for r in v),
     "a non-empty list of rates"),
    ("sha256", lambda v: isinstance(v, str) and _SHA256.fullmatch(v) is not None,
     "64 lowercase hex digits"),
    ("bytes", lambda v: is_int(v) and v >= 0, "an integer >= 0"),
)


def check_manifest(manifest, path: str | Path) -> dict:
    """``manifest`` (parsed JSON) if it is a well-formed manifest; otherwise one-line
    :class:`DatasetError` naming the file and the field. Shard paths must stay inside the dataset
    directory (relative, no ``..``)."""
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise DatasetError(f"{path}: not a rainbench manifest")
    if manifest.get("format_version") != MANIFEST_VERSION:
        raise DatasetError(f"{path}: unknown manifest format_version "
                           f"{_show(manifest.get('format_version'))}")
    if not isinstance(manifest.get("config"), dict):
        raise DatasetError(f"{path}: \"config\" must be an object, got "
                           f"{_show(manifest.get('config'))}")
    if not isinstance(manifest.get("complete"), bool):
        raise DatasetError(f"{path}: \"complete\" must be true or false, got "
                           f"{_show(manifest.get('complete'))}")
    shards = manifest.get("shards")
    if not isinstance(shards, list):
        raise DatasetError(f"{path}: \"shards\" must be a list of shard entries, got "
                           f"{_show(shards)}")
    seen = set()
    for number, entry in enumerate(shards):
        where = f"{path}: shards[{number}]"
        if not isinstance(entry, dict):
            raise DatasetError(f"{where}: expected an object, got {_show(entry)}")
        for key, valid, expected in _ENTRY_FIELDS:
            if key not in entry:
                raise DatasetError(f"{where}: \"{key}\" is missing")
            if not valid(entry[key]):
                raise DatasetError(f"{where}: \"{key}\" must be {expected}, got "
                                   f"{_show(entry[key])}")
        relative = PurePosixPath(entry["path"])
        if (relative.is_absolute() or ".." in relative.parts or not relative.parts
                or "\\" in entry["path"]):
            raise DatasetError(f"{where}: path {_show(entry['path'])} leaves the dataset "
                               "directory; shard paths must be relative paths inside it")
        if not entry["path"].isprintable():
            raise DatasetError(f"{where}: path {_show(entry['path'])} holds control "
                               "characters; shard paths must be printable")
        if relative in seen:
            raise DatasetError(f"{where}: {entry['path']} is listed twice")
        seen.add(relative)
    return manifest


def entry_problem(path: Path, entry: dict, handle) -> str | None:
    """What a shard file disagrees with in its manifest entry, checked without hashing it (a
    shard replaced, swapped or rewritten since the manifest was written): its size, scene and
    first frame; None when they agree. ``handle`` is the open shard."""
    size = path.stat().st_size
    if size != entry["bytes"]:
        return (f"{path}: {size} bytes, its manifest says {entry['bytes']} (changed since it was written: "
                "rainbench verify checks the dataset)")
    stored = []
    for key in ("scene_seed", "frame_offset"):
        value = handle.attrs.get(key)
        if value is None or np.ndim(value) != 0 or not np.issubdtype(np.asarray(value).dtype, np.integer):
            return f"{path}: its {key} attribute is {'missing' if value is None else 'not an integer'}"
        stored.append(int(value))
    if tuple(stored) != (entry["scene_seed"], entry["frame_offset"]):
        return (f"{path}: holds scene {stored[0]} from frame {stored[1]}, its manifest says scene "
                f"{entry['scene_seed']} from frame {entry['frame_offset']}")
    return None


def list_shards(data: str | Path | Sequence[str | Path]) -> list[Path]:
    """Shard paths of a dataset directory (manifest order; sorted names without a manifest),
    of one shard file, or of a list of shard files (kept in the given order)."""
    return [path for path, _ in listed_shards(data)]


def listed_shards(data: str | Path | Sequence[str | Path]) -> list[tuple[Path, dict | None]]:
    """:func:`list_shards`'s paths, in its order, each with its manifest entry (None for shard
    files, or in a directory without a manifest): the manifest is read once."""
    return read_listing(data)[0]


def read_listing(data: str | Path | Sequence[str | Path]) -> tuple[list[tuple[Path, dict | None]], dict | None]:
    """(:func:`listed_shards`, the manifest they come from or None), from one read."""
    manifest = None
    if isinstance(data, (list, tuple)):
        listed = [(Path(p), None) for p in data]
    else:
        root = Path(data)
        if root.is_file():
            listed = [(root, None)]
        elif root.is_dir():
            manifest = read_manifest(root)
            if manifest is not None:
                listed = [(root / entry["path"], entry) for entry in manifest["shards"]]
            else:
                listed = [(path, None) for path in sorted(root.glob(SHARD_GLOB))]
        else:
            raise DatasetError(f"{root}: no such dataset directory or shard")
    if not listed:
        raise DatasetError(f"{data}: no shards ({SHARD_GLOB}) found")
    missing = [str(path) for path, _ in listed if not path.is_file()]
    if missing:
        raise DatasetError(f"{missing[0]}: shard listed but missing")
    return listed, manifest


def verify_dataset(root: str | Path, images: bool = False) -> list[str]:
    """Problems of dataset ``root``, one line each, naming the file (empty list: all good).

    With ``images``, every stored image (and depth and instance map) of every shard that passes
    the other checks is decoded as well (:func:`undecodable_problem`): a chunk damaged in a file
    whose manifest was rewritten to match passes the sha256, not this."""
    root = Path(root)
    if not root.is_dir():  # not "root/manifest.json: missing" for a folder that is not there
        return [f"{root}: " + ("not a dataset folder (a file; a dataset is a folder with "
                               f"{MANIFEST})" if root.exists() else "no such dataset folder")]
    manifest = read_manifest(root)
    if manifest is None:
        return [f"{root / MANIFEST}: missing"]
    problems = []
    if not manifest.get("complete"):
        problems.append(f"{root / MANIFEST}: the dataset is incomplete (run the same command "
                        "again to finish it)")
    problems += _config_problems(root / MANIFEST, manifest["config"])
    problems += coverage_problems(root / MANIFEST, manifest)
    for entry in manifest["shards"]:
        path = root / entry["path"]
        if not path.is_file():
            problems.append(f"{path}: missing")
            continue
        if path.stat().st_size != entry["bytes"]:
            problems.append(f"{path}: {path.stat().st_size} bytes, manifest says {entry['bytes']}")
            continue
        if sha256_of(path) != entry["sha256"]:
            problems.append(f"{path}: sha256 differs from the manifest")
            continue
        try:
            with open_checked(path) as handle:
                rgb = handle["rgb"].shape
                offsets = handle["labels/offsets"].shape[0]
                disagreement = entry_problem(path, entry, handle)
                if disagreement is not None:
                    problems.append(disagreement)
                elif rgb[:2] != (len(entry["rates"]), entry["frames"]) or offsets != rgb[1] + 1:
                    problems.append(f"{path}: shapes disagree with the manifest (rgb {rgb})")
                elif not np.array_equal(np.asarray(handle["rates"][()], np.float32),
                                        np.asarray(entry["rates"], np.float64).astype(np.float32)):
                    # a shard stores float32 rates; the manifest the rates as given (12.3, not 12.300000190734863)
                    problems.append(f"{path}: its rates {_rates_text(handle['rates'][()])} disagree "
                                    f"with the manifest's {_rates_text(entry['rates'])}")
                elif images:
                    problem = undecodable_problem(handle, path)
                    if problem is not None:
                        problems.append(problem)
        except ShardFormatError as error:
            problems.append(str(error))
    return problems


def undecodable_problem(handle, path: str | Path) -> str | None:
    """The first image, depth map or instance map of an open shard that does not decode, as one
    line naming the file and the frame (None: every one decodes). About 4 ms an 800x600 image."""
    num_rates, frames = handle["rgb"].shape[:2]
    for frame in range(frames):
        for rate_row in range(num_rates):
            try:
                read_rgb(handle, rate_row, frame)
            except ShardFormatError as error:
                return str(error)
        for key in ("depth", "instance"):
            if key in handle:
                try:
                    handle[key][frame]
                except (OSError, ValueError, RuntimeError) as error:
                    reason = " ".join(str(error).split())
                    return f"{path}: /{key} chunk of frame {frame} is corrupt ({reason})"
    return None


def _rates_text(rates) -> str:
    return _show(",".join(f"{float(rate):g}" for rate in rates))


def _expected_shards(config: dict) -> dict[tuple[int, int], int] | None:
    """(scene seed, frame offset) -> frames of every shard the manifest's dataset ``config``
    has (the split of ``DatasetConfig.tasks``), or None when the config does not say (a
    manifest written by other tools, or fields out of range)."""
    fields = [config.get(key) for key in ("seed", "scenes", "frames", "frames_per_shard")]
    first = config.get("first_frame", 0)  # absent: a dataset from frame 0 (and older manifests)
    if not all(is_int(value) for value in fields + [first]):
        return None
    seed, scenes, frames, per_shard = fields
    if seed < 0 or first < 0 or not (1 <= scenes and 1 <= frames and 1 <= per_shard) \
            or scenes * math.ceil(frames / per_shard) > MAX_EXPECTED_SHARDS:
        return None
    return {(seed + scene, offset): min(per_shard, first + frames - offset)
            for scene in range(scenes) for offset in range(first, first + frames, per_shard)}


MAX_EXPECTED_SHARDS = 1_000_000
"""Most shards :func:`verify_dataset` enumerates from a manifest's config (beyond: not checked)."""


def _is_positive_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


_CONFIG_NUMBERS = (
    ("seed", lambda v: is_int(v) and v >= 0, "an integer >= 0"),
    ("rain_seed", lambda v: is_int(v) and v >= 0, "an integer >= 0"),
    ("scenes", lambda v: is_int(v) and v >= 1, "an integer >= 1"),
    ("frames", lambda v: is_int(v) and v >= 1, "an integer >= 1"),
    ("frames_per_shard", lambda v: is_int(v) and v >= 1, "an integer >= 1"),
    ("first_frame", lambda v: is_int(v) and v >= 0, "an integer >= 0"),
    ("clip_frames", lambda v: is_int(v) and v >= 1, "an integer >= 1"),
    ("width", lambda v: is_int(v) and v >= 1, "an integer >= 1"),
    ("height", lambda v: is_int(v) and v >= 1, "an integer >= 1"),
    ("fps", _is_positive_number, "a finite number > 0"),
    ("hfov_deg", _is_positive_number, "a finite number > 0"),
)
"""The numbers of a manifest's ``config`` that :func:`verify_dataset` checks where present (a
manifest written by rainbench has them; other tools' may lack some)."""


def _config_problems(manifest_path: Path, config: dict) -> list[str]:
    """The manifest config's numbers that no dataset has (a hand-edited ``"fps": NaN``), and a
    rate list that is not one."""
    problems = [f"{manifest_path}: config.{key} must be {expected}, got {_show(config[key])}"
                for key, valid, expected in _CONFIG_NUMBERS if key in config and not valid(config[key])]
    if "rates" in config:
        try:
            check_rate_list(config["rates"], "config.rates")
        except ValueError as error:
            problems.append(f"{manifest_path}: {error}")
    return problems


def coverage_problems(manifest_path: Path, manifest: dict) -> list[str]:
    """Manifest entries out of dataset order, whose file is named for another shard, or that the
    config does not describe (another scene, frame range or rate list), and, for a manifest that
    says it is complete, the config's shards it lacks (:func:`missing_shards_problem`)."""
    config = manifest["config"]
    expected = _expected_shards(config)
    if expected is None:
        return []
    rates = config.get("rates")
    rates_known = isinstance(rates, list) and all(
        isinstance(rate, (int, float)) and not isinstance(rate, bool) for rate in rates)
    problems = []
    previous = None
    for number, entry in enumerate(manifest["shards"]):
        where = f"{manifest_path}: shards[{number}] ({entry['path']})"
        key = (entry["scene_seed"], entry["frame_offset"])
        if previous is not None and key <= previous:
            problems.append(f"{where}: scene {key[0]} from frame {key[1]} is listed after scene {previous[0]} from "
                            f"frame {previous[1]} (shards are listed in dataset order: an image's index depends on it)")
        previous = key
        if PurePosixPath(entry["path"]).name != shard_name(*key):
            problems.append(f"{where}: the shard of scene {key[0]} from frame {key[1]} is named {shard_name(*key)}, "
                            f"not {PurePosixPath(entry['path']).name}")
        if expected.get(key) != entry["frames"]:
            problems.append(f"{where}: scene {key[0]}, frames {key[1]}..{key[1] + entry['frames'] - 1} "
                            "is not a shard of the manifest's config")
        elif rates_known and [float(rate) for rate in entry["rates"]] != [float(rate) for rate in rates]:
            problems.append(f"{where}: rates {_rates_text(entry['rates'])} disagree with the "
                            f"config's {_rates_text(rates)}")
    missing = missing_shards_problem(manifest_path, manifest)
    return problems + ([missing] if missing else [])


def missing_shards_problem(manifest_path: Path, manifest: dict) -> str | None:
    """For a manifest that says it is complete, the first of its config's shards it does not
    list (an edited manifest: readers would cover part of the dataset while it looks whole);
    None when it lists them all, says it is incomplete, or its config does not say."""
    expected = _expected_shards(manifest["config"])
    if expected is None or not manifest["complete"]:
        return None
    listed = {(entry["scene_seed"], entry["frame_offset"]) for entry in manifest["shards"]}
    missing = sorted(set(expected) - listed)
    if not missing:
        return None
    return (f"{manifest_path}: says complete but lists {len(expected) - len(missing)} of the config's "
            f"{len(expected)} shards (first missing: scene {missing[0][0]}, frame offset {missing[0][1]})")


def unlisted_shards(root: str | Path) -> list[Path]:
    """``.h5`` files under dataset ``root`` that its manifest does not list (so not part of the
    dataset: ``rainbench verify`` warns about them). Hidden temporary files, what hidden folders
    hold (a killed run's ``.pieces.tmp-PID``) and other datasets in subfolders (a folder with its
    own manifest: ``make paper``'s ``OUT/paper/jeon2022``) are not counted."""
    root = Path(root)
    manifest = read_manifest(root)
    listed = {root / entry["path"] for entry in manifest["shards"]} if manifest else set()
    others = {path.parent for path in root.rglob(MANIFEST) if path.parent != root}
    return sorted(path for path in root.rglob("*.h5")
                  if not any(part.startswith(".") for part in path.relative_to(root).parts) and path not in listed
                  and not any(parent in others for parent in path.parents))
