"""Campaign datasets on disk: sharded HDF5 files, checksums, the manifest, and the reader.

Layout of a campaign folder::

    DIR/manifest.json                 the config, its hash, package versions, subjects, splits,
                                      every finished shard with its SHA-256, counts
    DIR/shards/sSSSS_KKKKK.h5         images SSSS (subject) shard KKKKK, written atomically
    DIR/shards/sSSSS_KKKKK.h5.sha256  its checksum, written atomically after the shard
    DIR/pose_histogram.png            the sampled pose parameters against their ranges
    DIR/.simulate.lock                held while a run writes into DIR (sim.campaign.runner)

A shard is finished when both files exist and the checksum matches: a run killed at any
moment leaves only finished shards and temporary files (``.NAME.PID@HOST-XXXXXXXX.tmp.h5``,
:mod:`sim.core.atomic`), which ``--resume`` removes before it renders what is missing.

The reader checks every shard's SHA-256 against the manifest before it uses the shard's data
(once per shard file and process, :func:`verified_sha256`): a corrupt or truncated shard is a
:class:`DatasetError` naming the file and the command that renders it again.

Shard contents (``n`` images, ``H x W`` pixels):

=========================  ===================  ==============================================
dataset                    shape, dtype         meaning
=========================  ===================  ==============================================
``images/<physics>``       (n, H, W) float32    one array per ``[[physics]]`` entry (line: the
                                                line integral of mu, dimensionless)
``pose``                   (n, 4, 4) float64    volume pose T (docs/conventions.md)
``params``                 (n, 6) float64       phi, theta, psi (deg), tx, ty, tz (mm)
``projection``             (n, 3, 4) float64    K [R | t - R c], LPS mm -> pixels (u, v)
``image_index``            (n,) int64           index of the image within its subject
``projected_center``       (n, 2) float64       anatomy centre in pixels (u, v), optional
``bone_mask``              (n, H, W) uint8      1 where the ray crosses >= 1 mm of bone, optional
=========================  ===================  ==============================================

Attributes: ``subject``, ``shard``, ``start``, ``stop``, ``config_hash``, ``split``, ``name``, ``seed``
and ``pose_spawn_key`` (the poses are row ``image_index`` of ``PoseDistribution.sample`` drawn from
``SeedSequence(seed, spawn_key=(0, subject))``).
:func:`open_dataset` reads a folder without PyTorch; :class:`CampaignDataset` indexes images
across shards lazily and verifies each shard when it first opens it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from sim.core.atomic import atomic_path, remove_stale_temps, sha256_file, write_json
from sim.core.errors import InputError

FORMAT = "ctxreg-campaign"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
SHARD_DIR = "shards"


class DatasetError(InputError):
    """A campaign folder is missing, incomplete or corrupt; the message names the file."""


def shard_name(subject: int, shard: int) -> str:
    return f"s{subject:04d}_{shard:05d}.h5"


#: (real path, inode, size, mtime ns, ctime ns) -> SHA-256 of the files this process has hashed.
_HASHES: dict[tuple[str, int, int, int, int], str] = {}


def verified_sha256(path: Path) -> str:
    """SHA-256 of a file, computed once per process while the file stays the same (same
    inode, size, modification and status-change time); a changed file is hashed again."""
    st = os.stat(path)
    key = (os.path.realpath(path), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    digest = _HASHES.get(key)
    if digest is None:
        digest = _HASHES[key] = sha256_file(path)
    return digest


def write_shard(folder: Path, subject: int, shard: int, arrays: dict[str, np.ndarray],
                attrs: dict) -> tuple[str, str, int]:
    """Write one shard and then its checksum file, each atomically.

    Args:
        arrays: dataset path -> array (``images/<physics>`` paths create the group).
        attrs: scalar attributes (str, int, float).

    Returns:
        (file name, SHA-256 hex, size in bytes).
    """
    import h5py

    folder = Path(folder) / SHARD_DIR
    folder.mkdir(parents=True, exist_ok=True)
    name = shard_name(subject, shard)
    path = folder / name
    with atomic_path(path) as tmp:
        # track_times=False and a fixed layout keep the bytes identical for identical content
        with h5py.File(tmp, "w", track_order=True) as f:
            for key, value in attrs.items():
                f.attrs[key] = value
            for key, value in arrays.items():
                f.create_dataset(key, data=value, track_times=False)
    digest = verified_sha256(path)
    with atomic_path(folder / (name + ".sha256")) as tmp:
        tmp.write_text(digest + "\n")
    return name, digest, path.stat().st_size


def finished_shards(folder: Path) -> dict[str, str]:
    """Shard file name -> SHA-256 for every shard whose checksum file matches its content."""
    out = {}
    shard_dir = Path(folder) / SHARD_DIR
    if not shard_dir.is_dir():
        return out
    for sums in sorted(shard_dir.glob("*.h5.sha256")):
        h5 = sums.with_suffix("")
        if not h5.is_file():
            continue
        expected = sums.read_text().strip()
        if verified_sha256(h5) == expected:
            out[h5.name] = expected
    return out


def _shard_of(file_name: str) -> str:
    """The shard a file belongs to: ``s0001_00002.h5`` for itself, its ``.sha256`` and temporaries."""
    name = file_name.lstrip(".")
    return name[: name.index(".h5") + 3] if ".h5" in name else name


def remove_partial_files(folder: Path, only: set[str] | None = None) -> int:
    """Delete temporary files and shards without a matching checksum; returns how many.

    ``only``: shard names whose files may be touched (a part of the work cleans up its own
    shards only, while other parts write into the same folder). The stale temporary files of
    dead writers in ``folder`` itself (a manifest being written when the run was killed) go too.
    """
    remove_stale_temps(folder)
    shard_dir = Path(folder) / SHARD_DIR
    if not shard_dir.is_dir():
        return 0
    good = finished_shards(folder)
    removed = 0
    for p in shard_dir.iterdir():
        if only is not None and _shard_of(p.name) not in only:
            continue
        stale_tmp = ".tmp" in p.name
        bad_shard = p.suffix == ".h5" and p.name not in good
        orphan_sum = p.name.endswith(".sha256") and p.name[:-7] not in good
        if stale_tmp or bad_shard or orphan_sum:
            p.unlink()
            removed += 1
    return removed


def package_versions() -> dict[str, str]:
    from importlib import metadata

    out = {}
    for pkg in ("ctxreg", "mitsuba", "drjit", "numpy", "scipy", "h5py", "nibabel", "pydicom"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "absent"
    return out


def write_manifest(folder: Path, manifest: dict) -> None:
    write_json(Path(folder) / MANIFEST, manifest)


def read_manifest(folder: Path, name: str = MANIFEST) -> dict:
    path = Path(folder) / name
    if not path.is_file():
        raise DatasetError(f"{folder}: no {MANIFEST}; not a campaign folder (or the run never started)")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}: corrupt JSON ({e}); delete it and run `ctxreg simulate CAMPAIGN.toml "
                           f"--out {folder} --resume` to rebuild it from the shard files") from None
    if manifest.get("format") != FORMAT:
        raise DatasetError(f"{path}: not a {FORMAT} manifest")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise DatasetError(f"{path}: format version {manifest.get('format_version')} "
                           f"(this ctxreg reads {FORMAT_VERSION})")
    return manifest


@dataclass(frozen=True)
class _ShardRef:
    name: str
    subject: int
    start: int
    stop: int
    split: str


class CampaignDataset:
    """Images of a finished (or partly finished) campaign, indexed across shards.

    ``ds[i]`` returns a dict with ``images`` (physics name -> (H, W) float32), ``pose`` (4, 4),
    ``params`` (6,), ``projection`` (3, 4), ``subject``, ``split``, ``image_index`` and the
    optional outputs. Shards are opened lazily and kept open (``close()`` releases them).

    Every shard's size and SHA-256 are checked against the manifest before its data is used:
    when it is first opened, or for all shards at once with ``verify=True``. A file is hashed
    once per process (:func:`verified_sha256`), so opening the folder again costs nothing more.

    Raises:
        DatasetError: no or a corrupt manifest; an incomplete campaign (unless
            ``allow_incomplete``); a shard missing, truncated or corrupt (named, with the command
            that renders it again).
    """

    def __init__(self, folder: str | os.PathLike, *, verify: bool = False, allow_incomplete: bool = False):
        self.folder = Path(folder)
        self.manifest = read_manifest(self.folder)
        if not self.manifest.get("complete") and not allow_incomplete:
            raise DatasetError(f"{self.folder}: the campaign is incomplete "
                               f"({self.manifest.get('counts', {})}); finish it with --resume")
        subjects = {s["index"]: s for s in self.manifest["subjects"]}
        self.subjects = subjects
        refs = []
        for name, info in sorted(self.manifest["shards"].items()):
            path = self.folder / SHARD_DIR / name
            if not path.is_file():
                raise DatasetError(f"{path}: listed in the manifest but missing; {self._fix_hint()}")
            refs.append(_ShardRef(name, info["subject"], info["start"], info["stop"],
                                  subjects[info["subject"]]["split"]))
        self._refs = refs
        self._offsets = np.cumsum([0] + [r.stop - r.start for r in refs])
        self._open: dict[str, object] = {}
        if verify:
            for ref in refs:
                self.verify_shard(ref.name)

    def _fix_hint(self) -> str:
        source = self.manifest.get("config", {}).get("source", "CAMPAIGN.toml")
        return (f"render it again with `ctxreg simulate {source} --out {self.folder} --resume` "
                "(it keeps the good shards)")

    def verify_shard(self, name: str) -> None:
        """Check one shard file against the manifest (size, then SHA-256; hashed once per process).

        Raises:
            DatasetError: the file is missing, truncated or corrupt; the message names it.
        """
        info = self.manifest["shards"][name]
        path = self.folder / SHARD_DIR / name
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            raise DatasetError(f"{path}: listed in the manifest but missing; {self._fix_hint()}") from None
        if "bytes" in info and size != info["bytes"]:
            what = "truncated" if size < info["bytes"] else "longer than written"
            raise DatasetError(f"{path}: {what} ({size} bytes, the manifest says {info['bytes']}); "
                               f"{self._fix_hint()}")
        if verified_sha256(path) != info["sha256"]:
            raise DatasetError(f"{path}: checksum mismatch, the file is corrupt (SHA-256 differs from the "
                               f"manifest); {self._fix_hint()}")

    @property
    def physics(self) -> list[str]:
        return [p["name"] for p in self.manifest["config"]["physics"]]

    @property
    def splits(self) -> dict[str, list[int]]:
        """Split name -> subject indices."""
        out: dict[str, list[int]] = {}
        for s in self.subjects.values():
            out.setdefault(s["split"], []).append(s["index"])
        return out

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def _file(self, name: str):
        import h5py

        if name not in self._open:
            self.verify_shard(name)
            try:
                self._open[name] = h5py.File(self.folder / SHARD_DIR / name, "r")
            except OSError as e:  # verified, so the file changed since (or HDF5 cannot read it)
                raise DatasetError(f"{self.folder / SHARD_DIR / name}: cannot read the shard ({e}); "
                                   f"{self._fix_hint()}") from None
        return self._open[name]

    def __getitem__(self, i: int) -> dict:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"image {i} out of range for {n} images")
        i %= n
        k = int(np.searchsorted(self._offsets, i, side="right") - 1)
        ref = self._refs[k]
        j = i - int(self._offsets[k])
        f = self._file(ref.name)
        item = {
            "images": {p: np.asarray(f["images"][p][j]) for p in f["images"]},
            "subject": ref.subject,
            "split": ref.split,
        }
        for key in ("pose", "params", "projection", "image_index", "projected_center", "bone_mask"):
            if key in f:
                item[key] = np.asarray(f[key][j])
        return item

    def indices(self, split: str) -> np.ndarray:
        """Dataset indices of the images of one split."""
        idx = [np.arange(self._offsets[k], self._offsets[k + 1]) for k, r in enumerate(self._refs)
               if r.split == split]
        return np.concatenate(idx) if idx else np.zeros(0, np.int64)

    def iter_images(self, split: str | None = None) -> Iterator[dict]:
        """Images in dataset order (optionally one split), shard by shard."""
        for k, ref in enumerate(self._refs):
            if split is not None and ref.split != split:
                continue
            for i in range(int(self._offsets[k]), int(self._offsets[k + 1])):
                yield self[i]

    def arrays(self, key: str, split: str | None = None) -> np.ndarray:
        """One dataset (e.g. ``params`` or ``images/line``) concatenated over shards."""
        parts = [np.asarray(self._file(r.name)[key]) for r in self._refs
                 if split is None or r.split == split]
        if not parts:
            return np.zeros((0,))
        return np.concatenate(parts)

    def close(self) -> None:
        for f in self._open.values():
            f.close()
        self._open.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_dataset(folder: str | os.PathLike, *, verify: bool = False,
                 allow_incomplete: bool = False) -> CampaignDataset:
    """Open a campaign folder for reading (see :class:`CampaignDataset`); no PyTorch needed.

    ``verify``: check every shard's checksum now (else each when first used)."""
    return CampaignDataset(folder, verify=verify, allow_incomplete=allow_incomplete)
