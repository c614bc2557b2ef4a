#!/usr/bin/env python3
"""Feed camera frames to the Tweezer RL hardware agent from any program.

The agent reads frames as binary PGM ("P5"), one after another
(docs/hardware-agent.md, "Connecting a camera"). This script writes them
either on its standard output, when the agent starts it:

    [camera]
    source = "stream"
    [camera.stream]
    command = ["python3", "python/examples/camera_feed.py", "--rate", "20"]

or into a Unix socket the agent listens on, when it runs on its own:

    [camera.stream]
    socket = "/run/tweezer/camera.sock"

    python3 python/examples/camera_feed.py --socket /run/tweezer/camera.sock

As shipped it renders a demonstration sample (a trapped sphere at the centre
and free spheres drifting past) with nothing but the standard library. For
your camera, replace `DemoCamera` with a class whose `grab()` returns one
frame as (width, height, max_value, pixels): `pixels` holds the rows, one
byte per pixel when max_value < 256, else two, most significant first. With
a NumPy array `image` of 16-bit pixels that is
`image.astype(">u2").tobytes()`; of 8-bit pixels, `image.tobytes()`. For
example, with pylablib's Thorlabs uc480 driver:

    from pylablib.devices import uc480
    cam = uc480.UC480Camera()
    cam.start_acquisition()
    cam.wait_for_frame()
    image = cam.read_newest_image()

and with Micro-Manager through pycromanager, `core.snap_image()` then
`core.get_image()`. Run the camera at least as fast as the agent's control
rate: each control step waits for the next frame.
"""

import argparse
import os
import random
import socket
import sys
import time


def write_frame(out, width, height, max_value, pixels, captured=None):
    """Writes one binary PGM frame; `captured` (Unix seconds) says when it
    was exposed, so that the agent's latency counts from there."""
    header = b"P5\n"
    if captured is not None:
        header += b"# captured=%.6f\n" % captured
    header += b"%d %d\n%d\n" % (width, height, max_value)
    out.write(header)
    out.write(pixels)
    out.flush()


class DemoCamera:
    """A brightfield sample: dark discs (spheres, 24 px in radius) on a
    bright background, the trapped one still at the centre and the free
    ones drifting a pixel or two per frame, 8-bit."""

    RADIUS = 24
    BACKGROUND = 200
    SPHERE = 70

    def __init__(self, width, height, free, seed):
        self.width, self.height = width, height
        rng = random.Random(seed)
        self.free = []
        while len(self.free) < free:
            x, y = rng.uniform(0, width), rng.uniform(0, height)
            # Clear of the trapped sphere, so the demonstration starts clean.
            if (x - width / 2) ** 2 + (y - height / 2) ** 2 > (4 * self.RADIUS) ** 2:
                self.free.append([x, y, rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5)])
        self.row = bytes([self.BACKGROUND]) * width

    def centres(self):
        """Where the spheres are, the trapped one first."""
        return [(self.width / 2, self.height / 2)] + [(s[0], s[1]) for s in self.free]

    def grab(self):
        rows = [bytearray(self.row) for _ in range(self.height)]
        r = self.RADIUS
        for cx, cy in self.centres():
            for y in range(max(0, int(cy - r)), min(self.height, int(cy + r) + 1)):
                half = (r * r - (y + 0.5 - cy) ** 2) ** 0.5 if abs(y + 0.5 - cy) < r else 0
                x0, x1 = max(0, round(cx - half)), min(self.width, round(cx + half))
                if x1 > x0:
                    rows[y][x0:x1] = bytes([self.SPHERE]) * (x1 - x0)
        for s in self.free:
            s[0] = (s[0] + s[2]) % self.width
            s[1] = (s[1] + s[3]) % self.height
        return self.width, self.height, 255, b"".join(rows)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--socket", help="write into this Unix socket instead of standard output")
    parser.add_argument("--rate", type=float, default=20.0, help="frames per second")
    parser.add_argument("--size", default="640x480", help="frame size, WxH")
    parser.add_argument("--free", type=int, default=3, help="free spheres in the demonstration")
    parser.add_argument("--seed", type=int, default=0)
    # Misbehaviour on purpose, for the agent's tests.
    parser.add_argument("--stall-after", type=int, help="stop sending after this many frames, and hang")
    parser.add_argument("--exit-after", type=int, help="exit with status 3 after this many frames")
    parser.add_argument("--garbage-after", type=int, help="write a malformed frame after this many")
    args = parser.parse_args()

    width, height = (int(v) for v in args.size.split("x"))
    camera = DemoCamera(width, height, args.free, args.seed)
    if args.socket:
        connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        connection.connect(args.socket)
        out = connection.makefile("wb")
    else:
        out = os.fdopen(sys.stdout.fileno(), "wb", closefd=False)

    period = 1.0 / args.rate
    sent = 0
    next_time = time.monotonic()
    while True:
        if args.stall_after is not None and sent == args.stall_after:
            while True:
                time.sleep(3600)
        if args.exit_after is not None and sent == args.exit_after:
            sys.exit(3)
        if args.garbage_after is not None and sent == args.garbage_after:
            out.write(b"P6\n1 1\n255\n\x00\x00\x00")
            out.flush()
            while True:
                time.sleep(3600)
        captured = time.time()
        w, h, max_value, pixels = camera.grab()
        try:
            write_frame(out, w, h, max_value, pixels, captured)
        except BrokenPipeError:
            return  # the agent stopped reading
        sent += 1
        next_time += period
        time.sleep(max(0.0, next_time - time.monotonic()))


if __name__ == "__main__":
    main()
