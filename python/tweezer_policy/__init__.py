"""Tweezer RL policies in Python.

    import tweezer_policy
    policy = tweezer_policy.load("runs/lean-1/snapshots/best.safetensors")
    print(policy.snapshot.architecture, policy.snapshot.version)
    actions = policy.act([centres], [vector])  # centres: [[x, y], ...] FOV px
    # a network that reads motion takes each centre's displacement too:
    actions = policy.act([centres], [vector], [displacements])  # [dx, dy] or None

`load` checks the snapshot's metadata and checksum. Observations are what
the environment and the hardware agent give: the free spheres' centres in
FOV px and the target vector. The paper's CNN sees them rendered as the Rust
renderer draws them (`Renderer`); the set network reads each sphere's
offset from the trap, scaled by half the width of the field it was trained
on (`sphere_features`), and, where the snapshot's `inputs` is "motion",
each sphere's displacement since the previous step (`None` for one new to
the view)."""

import numpy as np

from . import numpy_policy
from .render import Renderer
from .snapshot import PAPER, SET, Snapshot, SnapshotError, read, weights_sha256

__all__ = [
    "MOTION_SCALE_PX", "PAPER", "SET", "Policy", "Renderer", "Snapshot", "SnapshotError", "load",
    "read", "sphere_features", "weights_sha256",
]

# Px of displacement per unit of the motion features (the Rust networks').
MOTION_SCALE_PX = np.float32(2.0)


def sphere_features(centres, fov_px, trained_fov_width, max_spheres, displacements=None):
    """One observation's set input: per free sphere (dx, dy, distance) from
    the trap (the FOV centre) in units of half the trained field's width;
    with more than `max_spheres`, the nearest. float32 [n, 3]. With
    `displacements` (one [dx, dy] px or None per centre, or an empty list
    where none is known), three more: the displacement over
    `MOTION_SCALE_PX`, and 1 for a sphere new to the view (moving 0)."""
    c = np.asarray(centres, dtype=np.float32).reshape(-1, 2)
    trap = np.float32(0.5) * np.asarray(fov_px, dtype=np.float32)
    scale = np.float32(0.5 * trained_fov_width)
    d = (c - trap) / scale
    features = np.concatenate([d, np.hypot(d[:, :1], d[:, 1:])], axis=1).astype(np.float32)
    if displacements is not None:
        if len(displacements) not in (0, len(c)):
            raise ValueError(f"{len(displacements)} displacements for {len(c)} centres")
        motion = np.zeros((len(c), 3), dtype=np.float32)
        motion[:, 2] = 1.0
        for k, m in enumerate(displacements):
            if m is not None:
                motion[k] = [np.float32(m[0]) / MOTION_SCALE_PX, np.float32(m[1]) / MOTION_SCALE_PX, 0.0]
        features = np.concatenate([features, motion], axis=1)
    if len(features) > max_spheres:
        features = features[np.argsort(features[:, 2], kind="stable")[:max_spheres]]
    return features


class Policy:
    """A snapshot's actor, acting in a field of view of `fov_px` (width,
    height) with spheres of `sphere_diameter_px`; `backend` is "numpy" or
    "torch"."""

    def __init__(self, snapshot, fov_px=None, sphere_diameter_px=54.0, backend="numpy"):
        self.snapshot = snapshot
        f = snapshot.fields
        if snapshot.architecture == SET:
            self.fov_px = tuple(fov_px or (f["fov_width"], f["fov_height"]))
            self.renderer = None
        else:
            self.fov_px = tuple(fov_px or (1280, 1024))
            self.renderer = Renderer(self.fov_px, (f["width"], f["height"]), sphere_diameter_px)
        if backend == "torch":
            from .torch_policy import TorchActor

            self._torch = TorchActor(snapshot)
        elif backend == "numpy":
            self._torch = None
        else:
            raise ValueError(f"backend must be 'numpy' or 'torch', not {backend!r}")

    def inputs(self, centres, displacements=None):
        """The network's input for a batch of observations' centres (and
        displacements, for a network that reads motion)."""
        if self.renderer is not None:
            return np.stack([self.renderer.render(c) for c in centres])[:, None]
        f = self.snapshot.fields
        if f["inputs"] == "motion":
            moves = displacements if displacements is not None else [[]] * len(centres)
        else:
            moves = [None] * len(centres)
        return [
            sphere_features(c, self.fov_px, f["fov_width"], f["max_spheres"], m)
            for c, m in zip(centres, moves)
        ]

    def act(self, centres, vectors, displacements=None):
        """Actions ([batch, 2], each in [-1, 1]) for a batch of observations:
        `centres[k]` the free spheres' centres, `vectors[k]` the target vector,
        and `displacements[k]` each centre's move since the previous step, px
        ([dx, dy], or None for a sphere new to the view), which a network that
        reads motion needs (without them every sphere counts as new)."""
        vectors = np.asarray(vectors, dtype=np.float32).reshape(-1, 2)
        if len(centres) != len(vectors):
            raise ValueError(f"{len(centres)} sets of centres but {len(vectors)} target vectors")
        if displacements is not None and len(displacements) != len(centres):
            raise ValueError(f"{len(centres)} sets of centres but {len(displacements)} of displacements")
        inputs = self.inputs(centres, displacements)
        if self._torch is not None:
            return self._torch(inputs, vectors).numpy()
        return numpy_policy.act(self.snapshot, inputs, vectors).astype(np.float32)


def load(path, fov_px=None, sphere_diameter_px=54.0, backend="numpy"):
    """The policy in the snapshot file at `path`, checked (see `Policy`)."""
    return Policy(read(path), fov_px, sphere_diameter_px, backend)
