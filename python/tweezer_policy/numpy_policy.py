"""The actors' forward passes in NumPy, layer for layer as `nets` defines
them (Burn: linear weights [in, out], convolution weights [out, in, kh, kw],
BatchNorm with its running statistics and epsilon 1e-5)."""

import numpy as np

from .snapshot import PAPER

BATCH_NORM_EPSILON = 1e-5


def linear(t, name, x):
    return x @ t[name + ".weight"] + t[name + ".bias"]


def relu(x):
    return np.maximum(x, 0.0)


def head(t, x):
    """Two hidden ReLU layers, then the output layer."""
    x = relu(linear(t, "head.fc1", x))
    x = relu(linear(t, "head.fc2", x))
    return linear(t, "head.out", x)


def conv2d(t, name, x, stride, padding):
    """x: [batch, in, h, w] → [batch, out, h', w']."""
    w, b = t[name + ".weight"], t[name + ".bias"]
    out_c, in_c, kh, kw = w.shape
    x = np.pad(x, ((0, 0), (0, 0), (padding, padding), (padding, padding)))
    n, _, h, wd = x.shape
    oh, ow = (h - kh) // stride + 1, (wd - kw) // stride + 1
    windows = np.lib.stride_tricks.sliding_window_view(x, (kh, kw), axis=(2, 3))
    windows = windows[:, :, ::stride, ::stride][:, :, :oh, :ow]  # [n, in, oh, ow, kh, kw]
    y = np.einsum("nchwkl,ockl->nohw", windows, w, optimize=True)
    return (y + b[None, :, None, None]).astype(np.float32)


def batch_norm(t, name, x):
    shape = (1, -1, 1, 1)
    mean = t[name + ".running_mean"].reshape(shape)
    std = np.sqrt(t[name + ".running_var"].reshape(shape) + BATCH_NORM_EPSILON)
    return (x - mean) / std * t[name + ".gamma"].reshape(shape) + t[name + ".beta"].reshape(shape)


def paper_actor(t, images, vectors):
    """images: [batch, 1, h, w]; vectors: [batch, 2] → actions [batch, 2]."""
    x = relu(batch_norm(t, "encoder.norm1", conv2d(t, "encoder.conv1", images, 4, 2)))
    x = relu(batch_norm(t, "encoder.norm2", conv2d(t, "encoder.conv2", x, 2, 1)))
    x = relu(batch_norm(t, "encoder.norm3", conv2d(t, "encoder.conv3", x, 1, 1)))
    x = relu(linear(t, "encoder.fc", x.reshape(x.shape[0], -1)))
    return np.tanh(head(t, np.concatenate([x, vectors], axis=1)))


def set_actor(t, pooling, sets, vectors):
    """sets: one [n_i, 3] (positions), [n_i, 6] (motion) or [n_i, 10] (goal) array of sphere
    features per observation;
    vectors: [batch, 2] → actions [batch, 2]."""
    pooled = []
    hidden = t["encoder.fc2.weight"].shape[1]
    for features in sets:
        if len(features):
            x = relu(linear(t, "encoder.fc1", features))
            x = relu(linear(t, "encoder.fc2", x))
            biggest, mean = x.max(axis=0), x.sum(axis=0) / len(features)
        else:
            biggest = mean = np.zeros(hidden, dtype=np.float32)
        pooled.append({"max_mean": [biggest, mean], "max": [biggest], "mean": [mean]}[pooling])
    x = np.stack([np.concatenate(p) for p in pooled]).reshape(len(sets), -1)
    return np.tanh(head(t, np.concatenate([x, vectors], axis=1)))


def act(snapshot, inputs, vectors):
    if snapshot.architecture == PAPER:
        return paper_actor(snapshot.tensors, inputs, vectors)
    return set_actor(snapshot.tensors, snapshot.fields["pooling"], inputs, vectors)
