"""The actors' forward passes in PyTorch (when it is installed), from the
same weights: linear weights transposed to PyTorch's [out, in]."""

import numpy as np
import torch
import torch.nn.functional as F

from .numpy_policy import BATCH_NORM_EPSILON
from .snapshot import PAPER


class TorchActor(torch.nn.Module):
    """A snapshot's actor as a PyTorch module (inference only)."""

    def __init__(self, snapshot):
        super().__init__()
        self.architecture = snapshot.architecture
        self.pooling = snapshot.fields.get("pooling")
        for name, array in snapshot.tensors.items():
            tensor = torch.from_numpy(np.array(array))
            if name.endswith(".weight") and tensor.dim() == 2:
                tensor = tensor.t().contiguous()
            self.register_buffer(name.replace(".", "__"), tensor)

    def _t(self, name):
        return getattr(self, name.replace(".", "__"))

    def _linear(self, name, x):
        return F.linear(x, self._t(name + ".weight"), self._t(name + ".bias"))

    def _head(self, x):
        x = F.relu(self._linear("head.fc1", x))
        x = F.relu(self._linear("head.fc2", x))
        return self._linear("head.out", x)

    def _block(self, k, x, stride, padding):
        x = F.conv2d(x, self._t(f"encoder.conv{k}.weight"), self._t(f"encoder.conv{k}.bias"),
                     stride=stride, padding=padding)
        x = F.batch_norm(x, self._t(f"encoder.norm{k}.running_mean"),
                         self._t(f"encoder.norm{k}.running_var"),
                         self._t(f"encoder.norm{k}.gamma"), self._t(f"encoder.norm{k}.beta"),
                         training=False, eps=BATCH_NORM_EPSILON)
        return F.relu(x)

    @torch.no_grad()
    def forward(self, inputs, vectors):
        vectors = torch.as_tensor(np.asarray(vectors, dtype=np.float32))
        if self.architecture == PAPER:
            x = torch.as_tensor(np.asarray(inputs, dtype=np.float32))
            x = self._block(1, x, 4, 2)
            x = self._block(2, x, 2, 1)
            x = self._block(3, x, 1, 1)
            x = F.relu(self._linear("encoder.fc", x.flatten(1)))
        else:
            pooled = []
            hidden = self._t("encoder.fc2.weight").shape[0]
            width = self._t("encoder.fc1.weight").shape[1]
            for features in inputs:
                f = torch.as_tensor(np.asarray(features, dtype=np.float32).reshape(-1, width))
                if len(f):
                    h = F.relu(self._linear("encoder.fc2", F.relu(self._linear("encoder.fc1", f))))
                    biggest, mean = h.max(0).values, h.sum(0) / len(f)
                else:
                    biggest = mean = torch.zeros(hidden)
                parts = {"max_mean": [biggest, mean], "max": [biggest], "mean": [mean]}
                pooled.append(torch.cat(parts[self.pooling]))
            x = torch.stack(pooled).reshape(len(inputs), -1)
        return torch.tanh(self._head(torch.cat([x, vectors], 1)))
