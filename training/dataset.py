"""Recorded simulations in HDF5: the schema, a writer and a reader.

Schema version 1 (docs/data.md has the full description):

    /steps    (S,)  STEP_DTYPE   one row per recorded step, in (seed, step) order
    /bodies   (SB,) BODY_DTYPE   body state at collide time, all steps concatenated
    /points   (SP,) CONTACT_DTYPE contact points after the solve (final impulse
                                  filled), all steps concatenated
    /trace    (ST,) float32      residual traces, all steps concatenated
    /oracle   (SP, 2) float32    optional (`generate --oracle`): each point's impulse
                                  (normal, tangent, N s) with this step solved from zero
                                  to convergence, rows as in /points

A step row holds offsets and counts into the three concatenated datasets, so
one step, or a slice of steps, reads without loading the file. Root attributes:
schema_version, scene (JSON), seeds, command, deepcontact_version, and physics (JSON: each
seed's [dt s, gravity_x, gravity_y m/s^2], where the world drew them from its seed; files without
it, and scenes, hold the scene's physics).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE

SCHEMA_VERSION = 1

STEP_DTYPE = np.dtype(
    [
        ("seed", "<i8"),
        ("step", "<i4"),
        ("body_offset", "<i8"),
        ("body_count", "<i4"),
        ("point_offset", "<i8"),
        ("point_count", "<i4"),
        ("trace_offset", "<i8"),
        ("velocity_iterations", "<i4"),  # max over islands; also the trace length
        ("velocity_iterations_sum", "<i4"),
        ("position_iterations", "<i4"),
        ("islands", "<i4"),
        ("solve_ms", "<f4"),  # wall clock: the only column that differs between runs
    ]
)

_CHUNK_ROWS = {"steps": 4096, "bodies": 16384, "points": 16384, "trace": 65536}

# How the writer compresses (h5py filters; any reader reads all three). One process writes a
# whole file, so its compression is the ceiling on simulations per second however many workers
# simulate: `deepcontact lab generate` times each (docs/scale.md). gzip is the smallest.
COMPRESSIONS = {
    "gzip": {"compression": "gzip", "compression_opts": 4, "shuffle": True},
    "lzf": {"compression": "lzf", "shuffle": True},
    "none": {},
}


class DatasetError(ValueError):
    """A data file that is missing, empty or not of this schema."""


class Writer:
    """Appends simulations to a new HDF5 file.

    Use as a context manager: the file is written under a temporary name and
    renamed to `path` only when the block exits cleanly, so an interrupted run
    leaves nothing under the final name.
    """

    def __init__(self, path: str | os.PathLike, *, scene: dict, seeds: list[int], command: str,
                 oracle: bool = False, compression: str = "gzip"):
        if compression not in COMPRESSIONS:
            raise ValueError(f"unknown compression {compression!r} (one of {', '.join(COMPRESSIONS)})")
        self.path = Path(path)
        self.compression = compression
        self.tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.part")
        self._meta = {"scene": scene, "seeds": seeds, "command": command}
        self._physics: dict[str, list[float]] = {}
        self.oracle = oracle
        self._file: h5py.File | None = None

    def __enter__(self) -> "Writer":
        from deepcontact import __version__

        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = h5py.File(self.tmp, "w")
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["scene"] = json.dumps(self._meta["scene"], sort_keys=True)
        f.attrs["seeds"] = np.asarray(self._meta["seeds"], dtype=np.int64)
        f.attrs["command"] = self._meta["command"]
        f.attrs["deepcontact_version"] = __version__
        for name, dtype in (("steps", STEP_DTYPE), ("bodies", BODY_DTYPE), ("points", CONTACT_DTYPE),
                            ("trace", np.dtype("<f4"))):
            f.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(_CHUNK_ROWS[name],),
                             **COMPRESSIONS[self.compression])
        if self.oracle:
            f.create_dataset("oracle", shape=(0, 2), maxshape=(None, 2), dtype="<f4",
                             chunks=(_CHUNK_ROWS["points"], 2), **COMPRESSIONS[self.compression])
        self._file = f
        return self

    def append(self, steps: np.ndarray, bodies: np.ndarray, points: np.ndarray, trace: np.ndarray,
               oracle: np.ndarray | None = None, physics: np.ndarray | None = None) -> None:
        """Append one simulation. Offsets in `steps` are relative to this
        simulation's arrays; they are shifted to file positions here. A file
        made with oracle=True takes the points' oracle impulses (P, 2) too;
        physics (3,) is the simulation's (dt s, gravity m/s^2)."""
        f = self._file
        if physics is not None and len(steps):
            self._physics[str(int(steps["seed"][0]))] = [float(v) for v in physics]
        if self.oracle != (oracle is not None):
            raise ValueError("this file records the oracle: every simulation needs it" if self.oracle
                             else "this file does not record the oracle")
        if oracle is not None:
            ds = f["oracle"]
            start = ds.shape[0]
            ds.resize((start + len(oracle), 2))
            ds[start:] = oracle
        steps = steps.copy()
        steps["body_offset"] += f["bodies"].shape[0]
        steps["point_offset"] += f["points"].shape[0]
        steps["trace_offset"] += f["trace"].shape[0]
        for name, rows in (("steps", steps), ("bodies", bodies), ("points", points), ("trace", trace)):
            ds = f[name]
            start = ds.shape[0]
            ds.resize((start + len(rows),))
            ds[start:] = rows

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and self._physics:
            self._file.attrs["physics"] = json.dumps(self._physics, sort_keys=True)
        self._file.close()
        if exc_type is None:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)


class Dataset:
    """Read access to a recorded file, a step (or a slice) at a time.

        ds = Dataset("data/train.h5")
        bodies, points, row = ds.step(10)      # one step
        for batch in ds.batches(32, shuffle=True, seed=0):
            ...                                 # lists of (bodies, points, row)
    """

    def __init__(self, path: str | os.PathLike):
        path = Path(path)
        if not path.exists():
            raise DatasetError(f"{path}: no such data file (make one with `deepcontact generate`)")
        try:
            self._file = h5py.File(path, "r")
        except OSError as exc:
            raise DatasetError(f"{path}: not an HDF5 file ({exc})") from None
        f = self._file
        version = f.attrs.get("schema_version")
        if version != SCHEMA_VERSION:
            raise DatasetError(f"{path}: schema version {version!r}, this reader knows {SCHEMA_VERSION}")
        self.path = path
        self.scene = json.loads(f.attrs["scene"])
        self.seeds = [int(s) for s in f.attrs["seeds"]]
        self.physics = {int(k): v for k, v in json.loads(f.attrs.get("physics", "{}")).items()}
        self.steps = f["steps"][:]  # the index is small: (S,) rows of 64 bytes
        self.has_oracle = "oracle" in f
        if len(self.steps) == 0:
            raise DatasetError(f"{path}: holds no steps")

    def __len__(self) -> int:
        return len(self.steps)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "Dataset":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def step(self, i: int) -> tuple[np.ndarray, np.ndarray, np.void]:
        """(bodies (B,) BODY_DTYPE, points (P,) CONTACT_DTYPE, step row)."""
        row = self.steps[i]
        b0, p0 = int(row["body_offset"]), int(row["point_offset"])
        bodies = self._file["bodies"][b0:b0 + int(row["body_count"])]
        points = self._file["points"][p0:p0 + int(row["point_count"])]
        return bodies, points, row

    def trace(self, i: int) -> np.ndarray:
        """Residual trace of step i: (velocity_iterations,) float32, N s."""
        row = self.steps[i]
        t0 = int(row["trace_offset"])
        return self._file["trace"][t0:t0 + int(row["velocity_iterations"])]

    def batches(self, batch_size: int, *, shuffle: bool = True, seed: int = 0,
                with_points_only: bool = True) -> Iterator[list[tuple[np.ndarray, np.ndarray, np.void]]]:
        """Yield lists of `batch_size` steps (the last may be shorter).

        with_points_only skips steps without contact points (nothing to learn).
        The order is fixed by `seed`, so an epoch can be replayed.
        """
        index = np.arange(len(self.steps))
        if with_points_only:
            index = index[self.steps["point_count"] > 0]
        if shuffle:
            np.random.default_rng(seed).shuffle(index)
        for start in range(0, len(index), batch_size):
            yield [self.step(int(i)) for i in index[start:start + batch_size]]


def differences(a: str | os.PathLike, b: str | os.PathLike) -> list[str]:
    """Where two recorded files differ, wall-clock timings (`solve_ms`) aside.

    Returns the names of the datasets, `steps` columns and root attributes
    (`command` aside: it names the run) that differ; [] when the files hold
    the same simulations bit for bit.
    """
    found = []
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        for name in ("scene", "seeds", "schema_version"):
            if not np.array_equal(fa.attrs[name], fb.attrs[name]):
                found.append(f"attribute {name}")
        for name in ("bodies", "points", "trace", "oracle"):
            if (name in fa) != (name in fb) or (name in fa and fa[name][:].tobytes() != fb[name][:].tobytes()):
                found.append(name)
        sa, sb = fa["steps"][:], fb["steps"][:]
        for field in STEP_DTYPE.names:
            if field != "solve_ms" and sa[field].tobytes() != sb[field].tobytes():
                found.append(f"steps.{field}")
    return found


def trained_on(paths) -> dict | None:
    """The envelope (deepcontact.envelope.Envelope.to_dict) of the worlds the data files at
    `paths` were recorded from, a card's `trained_on`; None where one of them cannot say (not a
    data file of this schema). A project scene's is read from its description; a user's world's
    (`generate --world`) from its records: a sample of its bodies and points, every seed's physics,
    and whether the world of its first seed has joints."""
    from deepcontact.envelope import Envelope

    envelopes = []
    for path in paths:
        try:
            with Dataset(path) as ds:
                envelopes.append(Envelope.from_scenes([ds.scene]) if ds.scene.get("kind") != "world"
                                 else _world_envelope(ds))
        except (DatasetError, OSError, KeyError, ValueError):
            return None
    if not envelopes:
        return None
    union = envelopes[0]
    for e in envelopes[1:]:
        union = union.union(e)
    return union.to_dict()


#: Rows of a world file's bodies and points its envelope reads (a strided sample of the file).
ENVELOPE_SAMPLE = 200_000


def _world_envelope(ds: "Dataset"):
    from deepcontact.envelope import Envelope
    from simclient import worlds

    f = ds._file
    sample = {name: f[name][::max(1, f[name].shape[0] // ENVELOPE_SAMPLE)] for name in ("bodies", "points")}
    world, _ = worlds.build_user_world(ds.scene["source"], ds.seeds[0])
    physics = list(ds.physics.values()) or [[ds.scene["solver"]["dt"], *world.gravity]]
    return Envelope.of_records(sample["bodies"], sample["points"], physics, joints=bool(len(world.joints)))
