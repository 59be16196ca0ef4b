"""The benchmark scripts stay runnable: each compiles, and each with a command line (argparse) imports what it
needs from vtgen and prints its usage. They are run by hand, so nothing else would notice one broken by a rename
or a typo until the next person needs its table."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

SCRIPTS = sorted((REPO / "benchmarks").glob("*.py"))


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_script_compiles_and_prints_its_usage(script):
    compile(script.read_text(), str(script), "exec")  # a SyntaxError names the file and line
    if "argparse" not in script.read_text():
        return  # e.g. train_loop_ab.py takes a checkout path, not options
    done = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120,
                          cwd=REPO)
    assert done.returncode == 0 and done.stdout.startswith("usage:"), (script.name, done.stderr[-2000:])


def test_every_benchmark_script_is_found():
    assert len(SCRIPTS) >= 20 and any(p.name == "unaligned_ablation.py" for p in SCRIPTS)


@pytest.mark.parametrize("antialias", [False, True])
def test_the_probe_rebuilds_a_checkpoints_discriminator_as_trained(antialias):
    """discriminator_probe reads the shape of the projection discriminator (width, depth, kernel, classes, whether it
    is anti-aliased) from its state dict alone, and the rebuilt one gives the trained one's logits."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    import torch
    from discriminator_probe import discriminator_from_state, lattice_contrast
    from vtgen.core.models import ProjectionDiscriminator

    torch.manual_seed(0)
    trained = ProjectionDiscriminator(5, ndf=8, layers=2, kernel=4, antialias=antialias).eval()
    images, labels = torch.rand(3, 3, 32, 32), torch.tensor([0, 4, 2])
    rebuilt = discriminator_from_state(trained.state_dict())
    assert sum(isinstance(m, torch.nn.Conv2d) for m in rebuilt.trunk) == 3 + antialias
    assert torch.equal(rebuilt(images, labels), trained(images, labels))
    index = torch.arange(64)
    on_grid = ((index[:, None] % 8 == 0) & (index[None, :] % 8 == 0)).double().numpy()
    assert lattice_contrast(1.0 + 99.0 * on_grid) == pytest.approx(2.0)  # 100x on the grid: log10 contrast 2
    assert lattice_contrast(torch.ones(64, 64).numpy()) == pytest.approx(0.0)


@pytest.mark.parametrize("key", ["conditioning.t2v", "class_gan.d_antialiass", "itrations"])
def test_a_variant_key_that_would_change_nothing_is_refused(default_params, key):
    """A misspelt or misplaced variant key used to fall into the preset's settings unread, so the 'variant' trained
    the default (a `conditioning.t2v=none` run gave the plain run's numbers to the digit)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from unaligned_ablation import run_variant

    with pytest.raises(ValueError, match=re.escape(repr(key.split(".", 1)[-1] if key.startswith("class_gan.") else key))):
        run_variant(default_params, None, None, "t2v", {key: "none"}, 0, 10, 1, Path("."), None)


def test_a_variant_may_set_an_optional_key_an_older_run_folder_lacks(default_params):
    """A run folder's params.yaml written before an optional key (here class_gan.d_antialias) existed: the schema
    allows the key, so the variant sets it (the run then fails later, on the missing pairs, not on the key)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from unaligned_ablation import run_variant

    del default_params["translation"]["class_gan"]["d_antialias"]
    with pytest.raises(TypeError) as error:  # pairs=None: past the variant's keys, into loading the data
        run_variant(default_params, None, None, "t2v", {"class_gan.d_antialias": True}, 0, 10, 1, Path("."), None)
    assert "variant key" not in str(error.value)


def test_read_rate_counts_the_inputs_whose_class_the_inferred_reader_reads(monkeypatch):
    """A feature reader fitted on red and blue tiles reads new red and blue tiles right (rate 1) and, asked
    against swapped names, wrong (rate 0); half the names swapped gives 0.5."""
    import torch

    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    from unaligned_ablation import read_rate
    from vtgen.core.conditioning import Conditioning
    from vtgen.core.readers import fit_feature_reader

    generator = torch.Generator().manual_seed(0)

    def tiles(colour, n):
        base = torch.tensor(colour, dtype=torch.float32)[None, :, None, None].expand(n, 3, 32, 32)
        return (base + 60 * torch.rand(n, 3, 32, 32, generator=generator)).clamp(0, 255).to(torch.uint8)

    train = torch.cat([tiles((180, 30, 30), 20), tiles((30, 30, 180), 20)])
    reader = fit_feature_reader(train, torch.tensor([0] * 20 + [1] * 20), 2)
    conditioning = Conditioning("inferred", ("red", "blue"), classifier=reader,
                                classifier_settings={"reader": "features", "size": 32})
    test = torch.cat([tiles((180, 30, 30), 4), tiles((30, 30, 180), 4)])
    names = ["red"] * 4 + ["blue"] * 4
    assert read_rate(conditioning, test, names) == 1.0
    assert read_rate(conditioning, test, names[::-1]) == 0.0
    assert read_rate(conditioning, test, ["red"] * 8) == 0.5


def test_goal_3_counts_the_figure_told_the_class_read_for_a_model_told_the_class(monkeypatch):
    """unaligned_goals: for a T2V model told the class, the told figure is shown as n/a and the GAN-test told the
    class read from the input is counted against 0.8 x the lower real-only accuracy: pass above, fail below;
    without that figure there is no such row; a model told nothing is counted on its GAN-test alone."""
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    from unaligned_goals import goal_rows

    def rows(read, conditioning="class"):
        visual = {"gan_test": 0.479, "real": 0.376} | ({} if read is None else {"gan_test_read": read})
        found = goal_rows({"t2v": {}}, {"visual": visual, "tactile": {"real": 0.25}}, {"t2v": conditioning})
        return {item: verdict for _, item, _, _, verdict in found if item.startswith("3 ")}

    interval = {"gan_test_read": 0.211, "gan_test_read_interval": {"low": 0.165, "high": 0.267, "n": 240}}
    found = goal_rows({"t2v": {}}, {"visual": {"real": 0.376, **interval}, "tactile": {"real": 0.263}}, {"t2v": "class"})
    assert [measured for _, item, measured, _, _ in found if "read" in item] == ["0.211 [0.165, 0.267], n 240"]
    told_nothing = {"gan_test": 0.267, "gan_test_interval": {"low": 0.196, "high": 0.352, "n": 120}}
    found = goal_rows({"v2t": {}}, {"tactile": {"real": 0.258, **told_nothing}, "visual": {"real": 0.3}}, {"v2t": "none"})
    assert [(measured, verdict) for _, item, measured, _, verdict in found if item.startswith("3 ")] == [
        ("0.267 [0.196, 0.352], n 120", "PASS")]  # bar 0.8 x 0.258

    assert rows(0.254) == {"3 GAN-test (visual), told the class (class)": "n/a",
                           "3 GAN-test (visual), told the class read from the input": "PASS"}  # bar 0.2
    assert rows(0.19)["3 GAN-test (visual), told the class read from the input"] == "FAIL"
    assert rows(None) == {"3 GAN-test (visual), told the class (class)": "n/a"}
    assert rows(0.19, "none") == {"3 GAN-test (visual)": "PASS"}  # its own GAN-test, 0.479


def test_the_ablation_counts_outputs_outside_their_class_brightness_range(monkeypatch):
    """The ablation's brightness column is the score stage's check: of four outputs of class a (real training
    targets at grey 200 and 220), one at 150 and one at 240 lie outside, so the share is 0.5."""
    import numpy as np
    import torch

    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    from unaligned_ablation import brightness_outside

    flat = lambda values: torch.tensor(values, dtype=torch.uint8)[:, None, None, None].expand(-1, 3, 4, 4)  # noqa: E731
    context = {"train_targets": flat([200, 220]), "train_target_classes": np.array(["a", "a"]),
               "test_targets": flat([210]), "test_target_classes": np.array(["a"])}
    assert brightness_outside(flat([150, 205, 215, 240]), np.array(["a"] * 4), context) == 0.5


def test_goal_rows_show_input_following_per_view_beside_item_1_without_counting_it(monkeypatch):
    """unaligned_goals: the score stage's following_<view> entries become one row per view, PASS where the
    permutation p is below 0.05 (the score stage's verdict), marked 'not counted' so the totals skip them."""
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    from unaligned_goals import goal_rows

    goals = {"v2t": {"following_pixels": {"value": -0.042, "low": -0.104, "high": 0.119, "p": 0.775, "n": 120},
                     "following_classifier": {"value": 0.115, "low": -0.091, "high": 0.107, "p": 0.018, "n": 120}}}
    found = {item: (measured, verdict) for _, item, measured, _, verdict in goal_rows(goals, {}) if "follow" in item}
    assert found == {"1 outputs follow their inputs within a class (pixels; not counted)": ("r -0.042 (p 0.775, n 120)", "FAIL"),
                     "1 outputs follow their inputs within a class (classifier; not counted)": ("r 0.115 (p 0.018, n 120)", "PASS")}


def test_paired_goal_rows_show_real_held_out_images_in_the_outputs_place(monkeypatch):
    """unaligned_goals: a paired row's target shows the score stage's real_heldout_minus for that baseline (how far
    real images themselves beat it at this n); the verdict still reads generated's interval alone."""
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    from unaligned_goals import goal_rows

    kid = {"generated": {"value": -0.05, "low": -0.43, "high": 0.34, "n": 72},
           "flat_mean_colour": {"value": 0.45, "low": 0.003, "high": 0.89, "n": 72},
           "generated_minus": {"flat_mean_colour": {"value": -0.438, "low": -1.03, "high": 0.158, "n": 72}},
           "real_heldout_minus": {"flat_mean_colour": {"value": -0.594, "low": -1.03, "high": -0.161, "n": 72}}}
    found = {item: (target, verdict) for _, item, _, target, verdict in goal_rows({"t2v": {"kid_classifier": kid}}, {})}
    assert found["2 paired KID minus flat_mean_colour"] == (
        "below 0 (real held-out in its place: -0.594 [-1.03, -0.161], n 72)", "FAIL")
    without = dict(kid, real_heldout_minus={})
    found = {item: target for _, item, _, target, _ in goal_rows({"t2v": {"kid_classifier": without}}, {})}
    assert found["2 paired KID minus flat_mean_colour"] == "below 0"
