"""The paper's networks and our TD3 update in PyTorch, timed as `learner
bench` times ours: batch 32, sampling counted, two warm-up updates, then the
mean over an even number of updates (every second one with the actor step
and the soft target updates). On the CPU by default; `--device cuda` keeps
the sampled pool on the host, as our replay is, and moves each batch to the
GPU, synchronising before every clock reading.

It mirrors `learner/src/td3.rs` step for step, the detached Q1 encoder in
the actor's loss included, so both sides do the same arithmetic. Images are
drawn once, before timing, as discs of the spec's size on the image grid
(rendering is not timed here; `learner bench` times its own).

Prints one JSON object.
"""

import argparse
import copy
import json
import os
import time

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


class Encoder(nn.Module):
    """conv 8/4/2, 4/2/1, 3/1/1 with BatchNorm and ReLU, then 512 wide."""

    def __init__(self, height, width):
        super().__init__()
        self.conv1 = nn.Conv2d(1, 32, 8, 4, 2)
        self.norm1 = nn.BatchNorm2d(32)
        self.conv2 = nn.Conv2d(32, 64, 4, 2, 1)
        self.norm2 = nn.BatchNorm2d(64)
        self.conv3 = nn.Conv2d(64, 64, 3, 1, 1)
        self.norm3 = nn.BatchNorm2d(64)
        with torch.no_grad():
            flat = self.convs(torch.zeros(1, 1, height, width)).numel()
        self.fc = nn.Linear(flat, 512)

    def convs(self, x):
        x = F.relu(self.norm1(self.conv1(x)))
        x = F.relu(self.norm2(self.conv2(x)))
        return F.relu(self.norm3(self.conv3(x)))

    def forward(self, x):
        return F.relu(self.fc(self.convs(x).flatten(1)))


def head(inputs, outputs):
    return nn.Sequential(nn.Linear(inputs, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(),
                         nn.Linear(64, outputs))


class Actor(nn.Module):
    def __init__(self, height, width):
        super().__init__()
        self.encoder = Encoder(height, width)
        self.head = head(514, 2)

    def forward(self, image, vector):
        return torch.tanh(self.head(torch.cat([self.encoder(image), vector], 1)))


class Critic(nn.Module):
    def __init__(self, height, width):
        super().__init__()
        self.encoder = Encoder(height, width)
        self.head = head(516, 1)

    def value(self, features, vector, action):
        return self.head(torch.cat([features, vector, action], 1))

    def forward(self, image, vector, action):
        return self.value(self.encoder(image), vector, action)


def frozen(module):
    """A target network: running BatchNorm statistics, no gradients."""
    target = copy.deepcopy(module).eval()
    for p in target.parameters():
        p.requires_grad_(False)
    return target


class Td3:
    gamma, tau, policy_noise, noise_clip, policy_delay = 0.99, 0.005, 0.2, 0.5, 2

    def __init__(self, height, width, device):
        self.actor, self.q1, self.q2 = (Actor(height, width).to(device),
                                        Critic(height, width).to(device),
                                        Critic(height, width).to(device))
        self.actor_target = frozen(self.actor)
        self.q1_target, self.q2_target = frozen(self.q1), frozen(self.q2)
        self.actor_optim = torch.optim.Adam(self.actor.parameters(), lr=1e-3, eps=1e-8)
        self.critic_optim = torch.optim.Adam(
            list(self.q1.parameters()) + list(self.q2.parameters()), lr=1e-3, eps=1e-8)
        self.updates = 0

    def critic_step(self, image, vector, action, reward, terminated, next_image, next_vector):
        with torch.no_grad():
            next_action = self.actor_target(next_image, next_vector)
            noise = (torch.randn_like(next_action) * self.policy_noise).clamp(
                -self.noise_clip, self.noise_clip)
            next_action = (next_action + noise).clamp(-1, 1)
            q_next = torch.min(self.q1_target(next_image, next_vector, next_action),
                               self.q2_target(next_image, next_vector, next_action))
            y = reward + self.gamma * (1 - terminated) * q_next
        loss = (F.mse_loss(self.q1(image, vector, action), y)
                + F.mse_loss(self.q2(image, vector, action), y))
        self.critic_optim.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_optim.step()
        self.updates += 1

    def actor_due(self):
        return self.updates % self.policy_delay == 0

    def actor_step(self, image, vector):
        pi = self.actor(image, vector)
        with torch.no_grad():
            features = self.q1.encoder(image)
        loss = -self.q1.value(features, vector, pi).mean()
        self.actor_optim.zero_grad(set_to_none=True)
        loss.backward()
        self.actor_optim.step()
        with torch.no_grad():
            for online, target in ((self.actor, self.actor_target), (self.q1, self.q1_target),
                                   (self.q2, self.q2_target)):
                for p, t in zip(online.parameters(), target.parameters()):
                    t.lerp_(p, self.tau)
                for b, t in zip(online.buffers(), target.buffers()):
                    t.copy_(b)


def disc_images(n, height, width, rng):
    """Binary images with about twelve discs of the spec's diameter (54 px
    of a 1280 x 1024 field of view) each, at the given resolution."""
    scale = width / 1280.0
    radius = 27.0 * scale
    ys, xs = np.mgrid[0:height, 0:width]
    images = np.zeros((n, 1, height, width), dtype=np.float32)
    for image in images:
        for _ in range(rng.integers(8, 17)):
            cx, cy = rng.uniform(0, width), rng.uniform(0, height)
            image[0][((xs + 0.5 - cx) ** 2 + (ys + 0.5 - cy) ** 2) <= radius ** 2] = 1.0
    return torch.from_numpy(images)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=256)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--updates", type=int, default=4)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--device", default="cpu", help="cpu, or cuda")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)

    def clock():
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return time.perf_counter()
    torch.manual_seed(7)
    rng = np.random.default_rng(7)

    pool = 512
    images = disc_images(pool, args.height, args.width, rng)
    vectors = torch.rand(pool, 2) * 2 - 1
    actions = torch.rand(pool, 2) * 2 - 1
    rewards = torch.randn(pool, 1)
    terminated = (torch.rand(pool, 1) < 0.02).float()

    def sample():
        i = torch.randint(0, pool, (args.batch_size,))
        j = (i + 1) % pool
        return tuple(t.to(device) for t in (images[i], vectors[i], actions[i], rewards[i],
                                             terminated[i], images[j], vectors[j]))

    td3 = Td3(args.height, args.width, device)

    def update(batch):
        td3.critic_step(*batch)
        if td3.actor_due():
            td3.actor_step(batch[0], batch[1])

    update(sample())
    update(sample())
    updates = max(2, args.updates + args.updates % 2)
    critic, actor = [], []
    started = clock()
    for _ in range(updates):
        batch = sample()
        t = clock()
        td3.critic_step(*batch)
        critic.append(clock() - t)
        if td3.actor_due():
            t = clock()
            td3.actor_step(batch[0], batch[1])
            actor.append(clock() - t)
    update_s = (clock() - started) / updates
    print(json.dumps({
        "peer": f"PyTorch {torch.__version__}",
        "update_ms_mean": update_s * 1e3,
        "critic_step_ms": 1e3 * sum(critic) / len(critic),
        "actor_step_ms": 1e3 * sum(actor) / len(actor),
        "resolution": [args.width, args.height],
        "batch_size": args.batch_size,
        "updates_timed": updates,
        "threads": torch.get_num_threads(),
        "device": (torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"),
    }))


if __name__ == "__main__":
    main()
