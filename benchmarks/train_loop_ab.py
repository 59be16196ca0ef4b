"""Seconds per training iteration of the `fast` preset for any checkout of vtgen, old or new.

    python benchmarks/train_loop_ab.py <checkout> [iterations]

Imports vtgen from ``<checkout>/src`` (a git worktree of an older commit works: its train module
was ``vtgen.train``), trains on 64 random in-memory tiles with params.yaml's `fast` preset, no
checkpoints, 2 threads, and prints s/it. Run two checkouts back to back to tell a code change
from a slower machine.
"""

import sys
import time
from pathlib import Path

import torch
import yaml

checkout, iterations = Path(sys.argv[1]).resolve(), int(sys.argv[2]) if len(sys.argv) > 2 else 200
sys.path.insert(0, str(checkout / "src"))
try:
    from vtgen.stages.train import PairData, train_translator
except ImportError:
    from vtgen.train import PairData, train_translator

torch.set_num_threads(2)
params = yaml.safe_load((Path(__file__).resolve().parents[1] / "params.yaml").read_text())
settings = dict(params["presets"]["fast"], iterations=iterations)
run = dict(params["translation"], resume=False, checkpoint_every=10**9)
images = (torch.rand((64, 3, 64, 64), generator=torch.Generator().manual_seed(0)) * 255).to(torch.uint8)
data = PairData(inputs=images, targets=images.flip(1).contiguous(), classes=["a"] * 64,
                aligned=torch.ones(64, dtype=torch.bool), pool_images=images, input_pool={"a": torch.arange(64)})
started = time.perf_counter()
train_translator(data, settings, run, "v2t", "all", checkpoint_dir=None, progress=False)
print(f"{checkout}: {(time.perf_counter() - started) / iterations:.4f} s/it over {iterations} iterations")
