"""Judging a training run's snapshots by what they translate (``class_gan.select_every``), and capacity auto's
class-paired validations (``translation.capacity.class_signal: recognition``).

:class:`Referee`: a real-only classifier of the target modality, trained on the distinct training targets, whose
penultimate features give the classifier-view FID (Heusel et al. 2017) of a snapshot's translated validation
inputs against those training targets. Class-paired data has no aligned validation pairs to score a snapshot
by; a distribution metric does not need them, nor does the classifier's probability of the input's class
(:meth:`Referee.recognition`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from vtgen.core.classifier import train_classifier
from vtgen.core.conditioning import Conditioning
from vtgen.core.distribution import classifier_encoder, fid, image_features
from vtgen.core.translation import translate


def distinct_images(images: torch.Tensor) -> torch.Tensor:
    """Row indices (sorted) of the first occurrence of each distinct image: class pairs repeat a target."""
    _, first = np.unique(images.reshape(len(images), -1).numpy(), axis=0, return_index=True)
    return torch.from_numpy(np.sort(first))


def at_side(images: torch.Tensor, side: int) -> torch.Tensor:
    """uint8 images resized (area) to ``side`` x ``side``; unchanged when they already are."""
    if images.shape[-1] == side:
        return images
    return F.interpolate(images.float(), size=(side, side), mode="area").round().clamp(0, 255).to(torch.uint8)


@dataclass(frozen=True)
class Referee:
    """Scores a generator by the classifier-view FID of its translations of ``inputs`` (the validation inputs,
    with their class names ``classes`` for a generator told the class) against ``reference`` (features of
    the real training targets), in ``encoder``'s view at ``side`` px. Lower is better. ``class_names`` are the
    classifier's outputs in order (:meth:`recognition`)."""

    encoder: torch.nn.Module
    reference: torch.Tensor
    side: int
    inputs: torch.Tensor
    classes: tuple[str, ...]
    class_names: tuple[str, ...] = ()

    def score(self, generator: torch.nn.Module, conditioning: Conditioning) -> float:
        labels = conditioning.labels(list(self.classes)) if conditioning.needs_labels else None
        was_training = generator.training
        generator.eval()
        made = translate(generator, self.inputs, conditioning=conditioning, labels=labels)
        generator.train(was_training)
        return fid(self.reference, image_features(self.encoder, at_side(made, self.side)))

    @torch.no_grad()
    def recognition(self, images: torch.Tensor, classes: list[str]) -> torch.Tensor:
        """Per image (uint8 N x 3 x S x S, its class name in ``classes``), the probability the referee's
        classifier gives that class (softmax of its logits, eval mode); 0 for a class it was not trained on."""
        model = self.encoder.model
        device = next(model.parameters()).device
        was_training = model.training
        model.eval()
        logits = torch.cat([model(at_side(images[i:i + 64], self.side).to(device)).float().cpu()
                            for i in range(0, len(images), 64)]) if len(images) else torch.empty(0, len(self.class_names))
        model.train(was_training)
        probabilities = torch.softmax(logits, dim=1)
        position = {name: i for i, name in enumerate(self.class_names)}
        return torch.tensor([float(probabilities[row, position[name]]) if name in position else 0.0
                             for row, name in enumerate(classes)], dtype=torch.float64)


def train_referee(targets: torch.Tensor, target_classes: list[str], inputs: torch.Tensor, input_classes: list[str],
                  classify: dict, seed: int) -> Referee:
    """A :class:`Referee` whose classifier is the classify stage's network (``classify``: size, width, epochs,
    batch_size, lr) trained, seeded with ``seed``, on the distinct ``targets`` (uint8, their class names
    ``target_classes``; index = sorted names), which are also its reference set."""
    names = sorted(set(target_classes))
    if len(names) < 2:
        raise ValueError(f"class_gan.select_every needs at least 2 classes for its referee classifier, got {names}")
    rows = distinct_images(targets)
    position = {name: i for i, name in enumerate(names)}
    labels = torch.tensor([position[target_classes[int(i)]] for i in rows], dtype=torch.int64)
    cfg = {"size": int(classify["size"]), **{k: classify[k] for k in ("width", "epochs", "batch_size", "lr")}}
    images = at_side(targets[rows], cfg["size"])
    run = train_classifier(images, labels, images, labels, len(names), cfg, seed)
    encoder = classifier_encoder(run.model.eval())
    return Referee(encoder, image_features(encoder, images), cfg["size"], inputs, tuple(input_classes), tuple(names))
