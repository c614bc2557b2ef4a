"""Reading a snapshot file: its metadata, checked, and its weights, verified
against the SHA-256 the learner wrote beside them."""

import hashlib
import struct
from dataclasses import dataclass, field

import numpy as np
from safetensors import safe_open

PAPER = "tweezer-paper-actor-v1"
SET = "tweezer-set-actor-v1"

# The hyper-parameters each architecture records, as metadata keys.
FIELDS = {
    PAPER: ("height", "width"),
    SET: ("sphere_hidden", "head_hidden", "pooling", "max_spheres", "fov_width", "fov_height"),
}
POOLINGS = ("max_mean", "max", "mean")
# What a set network reads of each sphere; snapshots without the field read
# positions.
INPUTS = ("positions", "motion", "goal")
# The axes a set network reads and acts along; snapshots without the field
# use the stage's.
FRAMES = ("stage", "goal")
# Px of displacement per unit of a set network's motion features where a
# snapshot does not record `motion_unit_px`: the spec's free-sphere speed.
DEFAULT_MOTION_UNIT_PX = 2.0
MAX_SIZE = 1 << 16
# Where a snapshot keeps the learner's two critics (`critic1.head.out.weight`).
# This package acts with the actor alone, as `actor act --actor-alone` does.
CRITIC_PREFIXES = ("critic1.", "critic2.")


class SnapshotError(ValueError):
    """A snapshot that cannot be used; the message names what is wrong."""


@dataclass
class Snapshot:
    """What a snapshot file holds."""

    architecture: str
    """`tweezer-paper-actor-v1` (the paper's CNN) or `tweezer-set-actor-v1`."""
    fields: dict
    """Its hyper-parameters: ints, `pooling` and (set network) `inputs` and
    `frame` as names, and (set network) `motion_unit_px` as a float."""
    version: int
    training_step: int
    tensors: dict = field(repr=False)
    """The actor's weights by Burn's module path (`encoder.fc1.weight`),
    float32; the critics' are left out. Linear weights are stored [in, out]:
    y = x @ W + b."""


def weights_sha256(tensors):
    """The digest the learner writes: for each tensor in name order, its
    name, its shape as little-endian u64s, its values as little-endian f32."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        array = tensors[name]
        digest.update(name.encode())
        for d in array.shape:
            digest.update(struct.pack("<Q", d))
        digest.update(np.ascontiguousarray(array, dtype="<f4").tobytes())
    return digest.hexdigest()


def _int(metadata, key):
    try:
        value = int(metadata[key])
    except (KeyError, ValueError):
        raise SnapshotError(f"snapshot metadata `{key}` is missing or malformed") from None
    return value


def read(path):
    """Reads and checks the snapshot at `path`."""
    try:
        with safe_open(str(path), framework="numpy") as f:
            metadata = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (OSError, ValueError, RuntimeError) as e:
        raise SnapshotError(f"not a safetensors snapshot: {path}: {e}") from None
    if metadata.get("format") != "tweezer-snapshot":
        raise SnapshotError("snapshot metadata `format` is missing or malformed")
    name = metadata.get("architecture")
    if name not in FIELDS:
        raise SnapshotError(f"unknown architecture `{name}` (known: {PAPER}, {SET})")
    fields = {}
    for key in FIELDS[name]:
        if key == "pooling":
            if metadata.get(key) not in POOLINGS:
                raise SnapshotError("architecture field `pooling` is missing or malformed")
            fields[key] = metadata[key]
            continue
        value = _int(metadata, key)
        if not 1 <= value <= MAX_SIZE:
            raise SnapshotError(f"architecture field `{key}` = {value}: must lie in [1, 65536]")
        fields[key] = value
    if name == SET:
        inputs = metadata.get("inputs", "positions")
        if inputs not in INPUTS:
            raise SnapshotError(
                f"architecture field `inputs` = {inputs!r}: this package reads {', '.join(INPUTS)}"
            )
        fields["inputs"] = inputs
        frame = metadata.get("frame", "stage")
        if frame not in FRAMES:
            raise SnapshotError(
                f"architecture field `frame` = {frame!r}: this package reads {', '.join(FRAMES)}"
            )
        fields["frame"] = frame
        unit = metadata.get("motion_unit_px", str(DEFAULT_MOTION_UNIT_PX))
        try:
            fields["motion_unit_px"] = float(unit)
        except ValueError:
            fields["motion_unit_px"] = float("nan")
        if not (np.isfinite(fields["motion_unit_px"]) and fields["motion_unit_px"] > 0):
            raise SnapshotError(f"architecture field `motion_unit_px` = {unit!r}: must be a positive number of px")
    for tensor, array in tensors.items():
        if array.dtype != np.float32:
            raise SnapshotError(f"snapshot tensor `{tensor}`: dtype {array.dtype}, expected float32")
    expected = metadata.get("weights_sha256")
    computed = weights_sha256(tensors)
    if expected != computed:
        raise SnapshotError(
            f"snapshot weights fail their checksum (expected {expected}, computed {computed})"
        )
    tensors = {k: v for k, v in tensors.items() if not k.startswith(CRITIC_PREFIXES)}
    return Snapshot(
        architecture=name,
        fields=fields,
        version=_int(metadata, "version"),
        training_step=_int(metadata, "training_step"),
        tensors=tensors,
    )
