"""Sphere centres → the binary image the paper's CNN sees, by the pixel rule
of the project's spec (docs/spec.md §2), as the Rust renderer draws it.

Image pixel (column j, row i) is lit iff its centre, s·(j + 0.5) and
s·(i + 0.5) in full-resolution FOV px (s: FOV width over image width), lies
within the sphere radius (inclusive) of the trapped sphere (the FOV centre)
or of a free sphere's centre. Computed in float64, as in Rust."""

import math

import numpy as np


class Renderer:
    """Renders a `fov_px` (width, height) field at `image` (width, height)
    resolution, spheres of `sphere_diameter_px`."""

    def __init__(self, fov_px=(1280, 1024), image=(320, 256), sphere_diameter_px=54.0):
        self.fov_px = (int(fov_px[0]), int(fov_px[1]))
        self.width, self.height = int(image[0]), int(image[1])
        self.scale = float(self.fov_px[0]) / float(self.width)
        self.radius = float(sphere_diameter_px) / 2.0
        self._columns = self.scale * (np.arange(self.width, dtype=np.float64) + 0.5)
        self._rows = self.scale * (np.arange(self.height, dtype=np.float64) + 0.5)

    def _disc(self, image, x, y):
        s, r = self.scale, self.radius
        j0 = max(0, math.floor((x - r) / s) - 1)
        j1 = min(self.width, math.ceil((x + r) / s) + 1)
        i0 = max(0, math.floor((y - r) / s) - 1)
        i1 = min(self.height, math.ceil((y + r) / s) + 1)
        if j0 >= j1 or i0 >= i1:
            return
        dx = self._columns[j0:j1] - x
        dy = self._rows[i0:i1] - y
        lit = dx[None, :] * dx[None, :] + dy[:, None] * dy[:, None] <= r * r
        image[i0:i1, j0:j1][lit] = 1.0

    def render(self, centres):
        """The image of free-sphere `centres` (FOV px, float32 as the
        environment gives them) and the trapped sphere: float32
        [height, width], 1 where lit."""
        image = np.zeros((self.height, self.width), dtype=np.float32)
        self._disc(image, 0.5 * self.fov_px[0], 0.5 * self.fov_px[1])
        for c in np.asarray(centres, dtype=np.float32).reshape(-1, 2):
            self._disc(image, float(c[0]), float(c[1]))
        return image
