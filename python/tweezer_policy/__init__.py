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
new to the view); "goal" also turns both towards the target vector. A
snapshot whose `frame` is "goal" reads the scene and the target vector, and
acts, along and across the heading to the target (`to_goal_frame`)."""

import numpy as np

from . import numpy_policy
from .render import Renderer
from .snapshot import DEFAULT_MOTION_UNIT_PX, PAPER, SET, Snapshot, SnapshotError, read, weights_sha256

__all__ = [
    "PAPER", "SET", "Policy", "Renderer", "Snapshot", "SnapshotError", "goal_frame",
    "heading", "load", "read", "sphere_features", "to_goal_frame", "weights_sha256",
]

def sphere_features(centres, fov_px, trained_fov_width, max_spheres, displacements=None, vector=None,
                    frame_heading=None, motion_unit_px=DEFAULT_MOTION_UNIT_PX):
    """One observation's set input: per free sphere (dx, dy, distance) from
    the trap (the FOV centre) in units of half the trained field's width;
    with more than `max_spheres`, the nearest. float32 [n, 3]. With
    `displacements` (one [dx, dy] px or None per centre, or an empty list
    where none is known), three more: the displacement over
    `motion_unit_px` (the snapshot's), and 1 for a sphere new to the view
    (moving 0). With
    the target `vector` too, four more: the offset and the displacement
    along and across the heading to the target (x where the vector is 0).
    With `frame_heading` (a network in the goal frame: `heading(vector)`),
    offsets and displacements are given along and across it."""
    c = np.asarray(centres, dtype=np.float32).reshape(-1, 2)
    trap = np.float32(0.5) * np.asarray(fov_px, dtype=np.float32)
    scale = np.float32(0.5 * trained_fov_width)
    d = (c - trap) / scale

    def turn(p):
        return p if frame_heading is None else _turned(p, frame_heading)

    offsets = turn(d)
    features = np.concatenate([offsets, np.hypot(offsets[:, :1], offsets[:, 1:])], axis=1).astype(np.float32)
    if displacements is not None:
        unit = np.float32(motion_unit_px)
        if len(displacements) not in (0, len(c)):
            raise ValueError(f"{len(displacements)} displacements for {len(c)} centres")
        motion = np.zeros((len(c), 3), dtype=np.float32)
        motion[:, 2] = 1.0
        for k, m in enumerate(displacements):
            if m is not None:
                motion[k] = [np.float32(m[0]) / unit, np.float32(m[1]) / unit, 0.0]
        features = np.concatenate([features, turn(motion[:, :2]), motion[:, 2:]], axis=1)
        if vector is not None:
            # Turned from the stage's axes, whatever the frame.
            features = np.concatenate([features, goal_frame(d, motion[:, :2], vector)], axis=1)
    if len(features) > max_spheres:
        features = features[np.argsort(features[:, 2], kind="stable")[:max_spheres]]
    return features


def heading(vector):
    """The unit vector along the target `vector` (x where it is 0): the x
    axis of the goal frame."""
    v = np.asarray(vector, dtype=np.float32).reshape(2)
    norm = np.hypot(v[0], v[1])
    return v / norm if norm > 1e-6 and np.isfinite(norm) else np.array([1.0, 0.0], dtype=np.float32)


def _turned(p, u):
    """Rows of `p` ([n, 2]) along and across the unit vector `u`."""
    ux, uy = np.float32(u[0]), np.float32(u[1])
    return np.stack([p[:, 0] * ux + p[:, 1] * uy, p[:, 1] * ux - p[:, 0] * uy], axis=1).astype(np.float32)


def goal_frame(offsets, moves, vector):
    """Offsets and moves ([n, 2] each) in the frame whose x axis points
    along `vector`, as [n, 4] float32: along, across, move along, across."""
    u = heading(vector)
    return np.concatenate([_turned(offsets, u), _turned(moves, u)], axis=1).astype(np.float32)


def to_goal_frame(vectors):
    """For a batch of target vectors ([batch, 2]): each turned into its own
    goal frame, and the function that turns the network's outputs there
    (tanh, [batch, 2]) into stage actions, as the Rust set actor does:
    widened by √2, turned back, and shrunk along their direction into
    [-1, 1]²."""
    u = np.stack([heading(v) for v in vectors]).reshape(-1, 2)
    turned = np.stack([_turned(v.reshape(1, 2), h)[0] for v, h in zip(vectors, u)]).reshape(-1, 2)

    def actions(raw):
        a = np.sqrt(np.float32(2.0)) * np.asarray(raw, dtype=np.float32)
        stage = np.stack([a[:, 0] * u[:, 0] - a[:, 1] * u[:, 1], a[:, 0] * u[:, 1] + a[:, 1] * u[:, 0]], axis=1)
        return stage / np.maximum(np.abs(stage).max(axis=1, keepdims=True), np.float32(1.0))

    return turned.astype(np.float32), actions


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
        frames = [heading(v) for v in vectors] if f["frame"] == "goal" else [None] * len(centres)
        return [
            sphere_features(c, self.fov_px, f["fov_width"], f["max_spheres"], m, v, h, f["motion_unit_px"])
            for c, m, v, h in zip(centres, moves, goals, frames)
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
        turn_back = None
        if self.snapshot.fields.get("frame") == "goal":
            vectors, turn_back = to_goal_frame(vectors)
        if self._torch is not None:
            raw = self._torch(inputs, vectors).numpy()
        else:
            raw = numpy_policy.act(self.snapshot, inputs, vectors)
        return (raw if turn_back is None else turn_back(raw)).astype(np.float32)


def load(path, fov_px=None, sphere_diameter_px=54.0, backend="numpy"):
    """The policy in the snapshot file at `path`, checked (see `Policy`)."""
    return Policy(read(path), fov_px, sphere_diameter_px, backend)
