"""SAC update speed on CPU and CUDA (run on a machine with a GPU; prints a Markdown table)."""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from alignrl.agents.replay import ReplayBuffer
from alignrl.agents.sac import SAC, SACConfig
from alignrl.transitions import Transition

CONFIGS = {
    "mlp": SACConfig(encoder_kwargs={"hidden": (256,)}),
    "gtrxl": SACConfig(encoder="gtrxl", hidden=(128, 128)),
}


def updates_per_second(device: str, config: SACConfig, batch: int, repeats: int = 100) -> float:
    torch.manual_seed(0)
    agent = SAC((8, 7), 2, 1, config, device)
    replay = ReplayBuffer(5000, (8, 7), 1, 2)
    rng = np.random.default_rng(0)
    n = 4000
    observation = rng.uniform(-1, 1, (n, 8, 7)).astype(np.float32)
    replay.add(
        Transition(
            observation,
            rng.uniform(-1, 1, (n, 1)),
            rng.uniform(-1, 1, (n, 2)),
            rng.normal(size=n),
            observation,
            rng.uniform(-1, 1, (n, 1)),
            np.zeros(n),
        )
    )
    for _ in range(10):
        agent.update(replay.sample(batch, rng))
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(repeats):
        agent.update(replay.sample(batch, rng))
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return repeats / (time.perf_counter() - start)


def main() -> int:
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    gpu = torch.cuda.get_device_name(0) if "cuda" in devices else "no GPU"
    print(f"torch {torch.__version__}, {gpu}")
    print("| encoder | batch | " + " | ".join(f"{d} updates/s" for d in devices) + " |")
    print("| --- | --- | " + " | ".join("---" for _ in devices) + " |")
    for name, config in CONFIGS.items():
        for batch in (256, 1024):
            rates = [updates_per_second(d, config, batch) for d in devices]
            print(f"| {name} | {batch} | " + " | ".join(f"{r:.0f}" for r in rates) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
