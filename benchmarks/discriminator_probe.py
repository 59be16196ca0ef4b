"""What a trained class-pair discriminator sees of the generator's fine patterns (a probe, not a test).

Three readings of one checkpoint's projection discriminator D (no DiffAugment: D's view of the images
themselves), on real test images y of the target modality (each under its class c) and the generator's
test outputs o (each under its input's class), from the .pt that ``unaligned_ablation.py --sheets`` wrote:

1. Scale: mean patch logit of real images and of outputs, so a change below can be read against their gap.
2. Where D looks: the power spectrum of D's input gradient, ∇_x mean D(x, c) (grey), by spatial period,
   beside the outputs' power over real images' per period, log10 (P_o / P_y); a band where the outputs
   carry extra power but D's gradient has little is a pattern D barely sees.
3. The shared pattern: m̂ = the outputs' mean fine detail (:func:`vtgen.core.translator.fine_detail`),
   normalised; each output's component along it, s_i = ⟨h(o_i), m̂⟩.
   Δ_remove = mean D(o_i − s_i·m̂) − D(o_i): > 0 when D would find the outputs more real without it;
   Δ_add = mean D(y + σ·m̂) − D(y), σ = rms s_i: < 0 when D penalises the pattern on real images;
   Δ_noise: the same with a random high-pass pattern of the same norm in place of m̂ (the control).
   Δ_add near 0 while Δ_noise is clearly negative means the pattern is in D's blind spot.
4. The lattice: how far the power at frequencies on the grid of multiples of side/8 cycles (periods 8, 4, 2 and their
   combinations, where stride-2 layers put their lattices) stands above the rest, in D's gradient and in the outputs.

    PYTHONPATH=src:benchmarks python benchmarks/discriminator_probe.py --run <run folder> --direction t2v \
        --checkpoint <ck>/t2v_<variant>_0/last.pt --outputs <sheets>/<run>_t2v_<variant>_0.pt --figure probe.png

The checkpoint is the one ``unaligned_ablation.py --checkpoints`` keeps (the discriminator of the last step;
the outputs come from the snapshot the referee kept, which may be earlier).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import yaml

from vtgen.core.domain import DIRECTIONS
from vtgen.core.models import ProjectionDiscriminator
from vtgen.core.translator import fine_detail
from vtgen.io.images import read_tiles
from vtgen.io.params import model_settings, validate_params
from vtgen.io.tables import read_table, SPLIT_COLUMNS

PERIOD_BANDS = (2.0, 2.5, 3.0, 4.0, 6.0, 8.0, 16.0, 64.0)  # band edges in pixels: [2, 2.5), [2.5, 3), ...


def discriminator_from_state(state: dict) -> ProjectionDiscriminator:
    """The projection discriminator a checkpoint's state dict describes (widths, kernel, depth and class count
    read from its tensors)."""
    convs = sorted({int(key.split(".")[1]) for key in state if key.startswith("trunk.")})
    antialias = len(convs) > 2 and convs[1] - convs[0] == 3  # full-side conv, LeakyReLU, blur, first strided conv
    first = state[f"trunk.{convs[0]}.parametrizations.weight.original"]
    strided = state[f"trunk.{convs[1 if antialias else 0]}.parametrizations.weight.original"]
    net = ProjectionDiscriminator(state["embedding.parametrizations.weight.original"].shape[0], ndf=strided.shape[0],
                                  layers=len(convs) - 1 - antialias, kernel=strided.shape[-1], in_channels=first.shape[1],
                                  class_head=any(key.startswith("class_head.") for key in state),
                                  antialias=antialias)
    net.load_state_dict(state)
    return net.eval().requires_grad_(False)


def to_unit(images: torch.Tensor) -> torch.Tensor:
    return images.float() / 127.5 - 1.0


def mean_power(planes: torch.Tensor) -> np.ndarray:
    """Mean over the N planes (N x S x S) of |FFT2(plane)|², S x S (numpy order)."""
    return torch.fft.fft2(planes).abs().pow(2).mean(dim=0).numpy()


def grey_power(images: torch.Tensor) -> np.ndarray:
    """:func:`mean_power` of each image's grey minus its mean (DC removed)."""
    grey = images.mean(dim=1)
    return mean_power(grey - grey.mean(dim=(1, 2), keepdim=True))


def mean_logit(net, images: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Each image's mean patch logit under its class (N)."""
    return net(images, labels).mean(dim=(1, 2, 3))


def gradient_power(net, images: torch.Tensor, labels: torch.Tensor) -> np.ndarray:
    """:func:`mean_power` of Σ_channels ∇_x mean-patch-logit over the images."""
    x = images.clone().requires_grad_(True)
    with torch.enable_grad():
        mean_logit(net, x, labels).sum().backward()
    return mean_power(x.grad.sum(dim=1))


def period_map(side: int) -> np.ndarray:
    """Spatial period in pixels of each frequency of a side x side FFT (inf at the DC term)."""
    f = np.fft.fftfreq(side)
    radius = np.hypot(f[:, None], f[None, :])
    with np.errstate(divide="ignore"):
        return 1.0 / radius


def lattice_contrast(plane: np.ndarray, step: int = 8) -> float:
    """Mean log10 of ``plane`` (a side x side power map) at the frequencies whose two indices are both multiples of
    ``step`` (DC excluded: the lattice of periods side/step and finer that stride-2 layers make) minus its mean
    log10 elsewhere; 0 when the lattice stands out no more than any other frequency."""
    index = np.arange(plane.shape[0])
    on = (index[:, None] % step == 0) & (index[None, :] % step == 0)
    on[0, 0] = False
    logs = np.log10(plane + 1e-12)
    off = ~on
    off[0, 0] = False
    return float(logs[on].mean() - logs[off].mean())


def band_sums(power: np.ndarray, periods: np.ndarray) -> list[float]:
    """``power`` summed over each band of :data:`PERIOD_BANDS` (DC excluded)."""
    return [float(power[(periods >= low) & (periods < high)].sum())
            for low, high in zip(PERIOD_BANDS[:-1], PERIOD_BANDS[1:])]


def pattern_changes(net, real, real_labels, outputs, output_labels, seed: int = 0) -> dict:
    """Δ_remove, Δ_add and Δ_noise of the module docstring, with the pattern's overlap share for scale."""
    detail = fine_detail(outputs)
    pattern = detail.mean(dim=0)
    unit = pattern / pattern.norm()
    along = (detail * unit).flatten(1).sum(dim=1)  # s_i
    sigma = float(along.pow(2).mean().sqrt())
    g = torch.Generator().manual_seed(seed)
    noise = fine_detail(torch.randn(1, *unit.shape, generator=g))[0]
    noise = noise / noise.norm()
    base_out, base_real = mean_logit(net, outputs, output_labels), mean_logit(net, real, real_labels)
    removed = mean_logit(net, outputs - along[:, None, None, None] * unit, output_labels)
    added = mean_logit(net, (real + sigma * unit).clamp(-1, 1), real_labels)
    noised = mean_logit(net, (real + sigma * noise).clamp(-1, 1), real_labels)
    energy = float(along.pow(2).sum() / detail.pow(2).sum())
    return {"remove": float((removed - base_out).mean()), "add": float((added - base_real).mean()),
            "noise": float((noised - base_real).mean()), "sigma": sigma, "share": energy}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="run folder holding params.yaml and data/pairs")
    parser.add_argument("--direction", choices=list(DIRECTIONS), required=True)
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--outputs", type=Path, required=True,
                        help="the generator's test outputs (.pt of unaligned_ablation --sheets)")
    parser.add_argument("--figure", type=Path)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    params = validate_params(yaml.safe_load((args.run / "params.yaml").read_text()))
    size = model_settings(params)["size"]
    source, target = DIRECTIONS[args.direction]
    splits = read_table(args.run / "data" / "pairs" / "splits.parquet", SPLIT_COLUMNS, "splits")
    state = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    net = discriminator_from_state(state["discriminator"])
    classes = sorted(set(splits[(splits["split"] == "train") & (splits["modality"] == target)]["class"]))
    real_rows = splits[(splits["split"] == "test") & (splits["modality"] == target)].sort_values("path")
    input_rows = splits[(splits["split"] == "test") & (splits["modality"] == source)].sort_values("path")
    real = to_unit(read_tiles(list(real_rows["path"]), size, args.run))
    outputs = to_unit(torch.load(args.outputs))
    if len(outputs) != len(input_rows):
        parser.error(f"{args.outputs}: {len(outputs)} outputs, but {len(input_rows)} test {source} inputs")
    real_labels = torch.tensor([classes.index(c) for c in real_rows["class"]])
    output_labels = torch.tensor([classes.index(c) for c in input_rows["class"]])
    with torch.no_grad():
        logit_real = float(mean_logit(net, real, real_labels).mean())
        logit_out = float(mean_logit(net, outputs, output_labels).mean())
        changes = pattern_changes(net, real, real_labels, outputs, output_labels)
    print(f"# {args.checkpoint} (step {state['step']}), no augmentation. Mean patch logit: real test {target} "
          f"{logit_real:+.3f} (n = {len(real)}), outputs {logit_out:+.3f} (n = {len(outputs)}); gap "
          f"{logit_real - logit_out:+.3f}")
    print(f"# shared pattern (the outputs' mean fine detail): {changes['share']:.3f} of the outputs' fine-detail energy, "
          f"rms component {changes['sigma']:.3f}\n"
          f"# Δ_remove {changes['remove']:+.4f} (outputs without it), Δ_add {changes['add']:+.4f} (real images with it), "
          f"Δ_noise {changes['noise']:+.4f} (real images with high-pass noise of the same norm)")
    periods = period_map(size)
    grad_real = gradient_power(net, real, real_labels)
    grad_out = gradient_power(net, outputs, output_labels)
    power_real, power_out = grey_power(real), grey_power(outputs)
    columns = [band_sums(p, periods) for p in (grad_real, grad_out, power_real, power_out)]
    totals = [sum(c) for c in columns[:2]]
    print("| period band (px) | D gradient share, real | D gradient share, outputs | log10 power outputs / real |\n"
          "|---|---|---|---|")
    for i, (low, high) in enumerate(zip(PERIOD_BANDS[:-1], PERIOD_BANDS[1:])):
        ratio = np.log10(columns[3][i] / max(columns[2][i], 1e-12))
        print(f"| [{low:g}, {high:g}) | {columns[0][i] / totals[0]:.3f} | {columns[1][i] / totals[1]:.3f} | {ratio:+.2f} |")
    print(f"# lattice contrast (log10 power at frequencies on the step-8 grid over elsewhere): D gradient on real images "
          f"{lattice_contrast(grad_real):+.2f}, on outputs {lattice_contrast(grad_out):+.2f}; outputs' power "
          f"{lattice_contrast(power_out):+.2f}, real images' {lattice_contrast(power_real):+.2f}")
    if args.figure:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        panels = [("log10 D gradient power, real images", np.log10(grad_real + 1e-12)),
                  ("log10 power, outputs / real", np.log10((power_out + 1e-9) / (power_real + 1e-9))),
                  ("outputs' mean fine detail (grey)", None)]
        fig, axes = plt.subplots(1, 3, figsize=(14, 4.4))
        for ax, (title, plane) in zip(axes, panels):
            if plane is None:
                pattern = fine_detail(outputs).mean(dim=0).mean(dim=0).numpy()
                limit = np.abs(pattern).max()
                image = ax.imshow(pattern, cmap="coolwarm", vmin=-limit, vmax=limit)
            else:
                image = ax.imshow(np.fft.fftshift(plane), cmap="magma" if "gradient" in title else "coolwarm",
                                  **({} if "gradient" in title else {"vmin": -2, "vmax": 2}))
                ax.set_xlabel("horizontal frequency (centre = 0)")
            ax.set_title(title, fontsize=9)
            fig.colorbar(image, ax=ax, fraction=0.046)
        fig.suptitle(f"{args.checkpoint.parent.name}: discriminator at step {state['step']}", fontsize=10)
        fig.tight_layout()
        fig.savefig(args.figure, dpi=110)
        print(f"# figure: {args.figure}")


if __name__ == "__main__":
    main()
