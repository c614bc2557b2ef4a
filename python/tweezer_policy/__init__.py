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
on (`sphere_features`), and, where the snapshot's `inputs` is "motion" or
"goal", each sphere's displacement since the previous step (`None` for one
new to the view); "goal" also turns both towards the target vector."""

import numpy as np

from . import numpy_policy
from .render import Renderer
from .snapshot import PAPER, SET, Snapshot, SnapshotError, read, weights_sha256

__all__ = [
    "MOTION_SCALE_PX", "PAPER", "SET", "Policy", "Renderer", "Snapshot", "SnapshotError", "goal_frame",
    "load", "read", "sphere_features", "weights_sha256",
]

# Px of displacement per unit of the motion features (the Rust networks').
MOTION_SCALE_PX = np.float32(2.0)


def sphere_features(centres, fov_px, trained_fov_width, max_spheres, displacements=None, vector=None):
    """One observation's set input: per free sphere (dx, dy, distance) from
    the trap (the FOV centre) in units of half the trained field's width;
    with more than `max_spheres`, the nearest. float32 [n, 3]. With
    `displacements` (one [dx, dy] px or None per centre, or an empty list
    where none is known), three more: the displacement over
    `MOTION_SCALE_PX`, and 1 for a sphere new to the view (moving 0). With
    the target `vector` too, four more: the offset and the displacement
    along and across the heading to the target (x where the vector is 0)."""
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
        if vector is not None:
            features = np.concatenate([features, goal_frame(d, motion[:, :2], vector)], axis=1)
    if len(features) > max_spheres:
        features = features[np.argsort(features[:, 2], kind="stable")[:max_spheres]]
    return features


def goal_frame(offsets, moves, vector):
    """Offsets and moves ([n, 2] each) in the frame whose x axis points
    along `vector`, as [n, 4] float32: along, across, move along, across."""
    v = np.asarray(vector, dtype=np.float32).reshape(2)
    norm = np.hypot(v[0], v[1])
    u = v / norm if norm > 1e-6 and np.isfinite(norm) else np.array([1.0, 0.0], dtype=np.float32)
    ux, uy = np.float32(u[0]), np.float32(u[1])

    def turned(p):
        return np.stack([p[:, 0] * ux + p[:, 1] * uy, p[:, 1] * ux - p[:, 0] * uy], axis=1)

    return np.concatenate([turned(offsets), turned(moves)], axis=1).astype(np.float32)


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

    def inputs(self, centres, vectors, displacements=None):
        """The network's input for a batch of observations' centres (with
        their target vectors and displacements, for a network that reads
        motion or goal)."""
        if self.renderer is not None:
            return np.stack([self.renderer.render(c) for c in centres])[:, None]
        f = self.snapshot.fields
        if f["inputs"] in ("motion", "goal"):
            moves = displacements if displacements is not None else [[]] * len(centres)
        else:
            moves = [None] * len(centres)
        goals = vectors if f["inputs"] == "goal" else [None] * len(centres)
        return [
            sphere_features(c, self.fov_px, f["fov_width"], f["max_spheres"], m, v)
            for c, m, v in zip(centres, moves, goals)
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
        inputs = self.inputs(centres, vectors, displacements)
        if self._torch is not None:
            return self._torch(inputs, vectors).numpy()
        return numpy_policy.act(self.snapshot, inputs, vectors).astype(np.float32)


def load(path, fov_px=None, sphere_diameter_px=54.0, backend="numpy"):
    """The policy in the snapshot file at `path`, checked (see `Policy`)."""
    return Policy(read(path), fov_px, sphere_diameter_px, backend)
