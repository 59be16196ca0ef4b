"""What a generator is told besides its input image.

Touch cannot tell colour, and a photo of one fabric does not say how hard its threads press; a
user usually knows the class, and may have a reference photo. A :class:`Conditioning` turns a batch
of input images and their class indices into the generator's input, the *condition*:

* ``none`` - the input image alone (the paper's setting, Lee et al. 2019);
* ``class`` - the input plus one constant map per class, 1 on the image's class and 0 elsewhere
  (a one-hot map, as in conditional GANs, Mirza & Osindero 2014);
* ``reference`` - the class maps plus one real image of the target modality of that class, the
  appearance reference of VisGel (Li et al. 2019) and Gao et al. 2023;
* ``inferred`` - trained as ``class`` (the training pairs' classes are known), but when translating the
  generator is told the class a classifier of the *input* modality reads from the input itself (its most
  probable class): the classify stage's network, or a reader of hand-crafted features
  (:mod:`vtgen.core.readers`, ``translation.inferred_reader``). It is never told the true class of what it
  translates; on class-paired data, where the class is all that links a photo to a touch, it is told what
  its input says, so its output can be no more recognisable than its input is (issue 24, goal 3).

The discriminator sees the same condition stacked with the real or generated image
(:func:`vtgen.core.models.conditional_pair`), so both networks know what was asked for.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from vtgen.core.classifier import make_classifier
from vtgen.core.readers import FeatureReader

CONDITIONINGS = ("none", "class", "reference", "inferred")
INPUT_READERS = ("network", "features")  # what reads the input's class for ``inferred`` (translation.inferred_reader)


@dataclass(frozen=True)
class Conditioning:
    """``kind`` (one of :data:`CONDITIONINGS`), the class names in index order, for ``reference`` one
    uint8 ``K x 3 x S x S`` reference image per class (same order), and for ``inferred`` the input-modality
    classifier, eval mode: :func:`vtgen.core.classifier.make_classifier` with ``classifier_settings``, or, when
    those settings say ``reader: features``, a :class:`vtgen.core.readers.FeatureReader`."""

    kind: str = "none"
    classes: tuple[str, ...] = ()
    references: torch.Tensor | None = None
    classifier: torch.nn.Module | None = None
    classifier_settings: dict | None = None

    def __post_init__(self) -> None:
        if self.kind not in CONDITIONINGS:
            raise ValueError(f"unknown conditioning '{self.kind}' (allowed: {', '.join(CONDITIONINGS)})")
        if self.kind != "none" and not self.classes:
            raise ValueError(f"conditioning '{self.kind}' needs at least one class")
        if len(set(self.classes)) != len(self.classes):
            raise ValueError(f"conditioning classes repeat: {list(self.classes)}")
        if self.kind == "reference":
            refs = self.references
            if refs is None or refs.dim() != 4 or refs.shape[0] != len(self.classes) or refs.shape[1] != 3 \
                    or refs.dtype != torch.uint8:
                shape = None if refs is None else (tuple(refs.shape), refs.dtype)
                raise ValueError(f"conditioning 'reference' needs a uint8 K x 3 x S x S tensor with K = "
                                 f"{len(self.classes)} classes, got {shape}")
        if self.kind == "inferred" and (self.classifier is None or self.classifier_settings is None):
            raise ValueError("conditioning 'inferred' needs the input-modality classifier and its settings")

    @property
    def needs_labels(self) -> bool:
        """Whether translating needs each image's class (``inferred`` reads it from the image)."""
        return self.kind in ("class", "reference")

    @property
    def extra_channels(self) -> int:
        """Channels the condition adds to the 3 of the input image."""
        if self.kind == "none":
            return 0
        return len(self.classes) + (3 if self.kind == "reference" else 0)

    def labels(self, class_names) -> torch.Tensor:
        """Class indices (int64) of ``class_names``; ValueError naming any class the model does not know."""
        index = {name: i for i, name in enumerate(self.classes)}
        unknown = sorted({c for c in class_names if c not in index})
        if unknown and self.kind != "none":
            raise ValueError(f"class {', '.join(map(repr, unknown))} unknown to this model "
                             f"(it knows {', '.join(self.classes)})")
        return torch.tensor([index.get(c, 0) for c in class_names], dtype=torch.int64)

    def condition(self, x: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """``x`` (N x 3 x S x S in [-1, 1]) with this conditioning's channels appended: N x (3 + extra) x S x S.

        Class maps are 1 (the image's class) or -1 (the others), in the images' range; a reference is
        resized (area) to S when its side differs. ``inferred`` with ``labels`` (training) maps them as
        ``class`` does; with None (translating) it maps the class the classifier reads from ``x``, the argmax of
        :meth:`probabilities`: the same one-hot maps the generator was trained on, never a softer mixture.
        """
        if self.kind == "none":
            return x
        n, _, height, width = x.shape
        if labels is None:
            if self.kind != "inferred":
                raise ValueError(f"conditioning '{self.kind}' needs each image's class")
            labels = self.probabilities(x).argmax(dim=1)
        onehot = F.one_hot(labels.to(x.device), len(self.classes)).to(x.dtype) * 2 - 1
        parts = [x, onehot[:, :, None, None].expand(n, len(self.classes), height, width)]
        if self.kind == "reference":
            refs = self.references.to(x.device)[labels.to(x.device)].float() / 127.5 - 1.0
            if refs.shape[-2:] != (height, width):
                refs = F.interpolate(refs, size=(height, width), mode="area")
            parts.append(refs.to(x.dtype))
        return torch.cat(parts, dim=1)

    @torch.no_grad()
    def probabilities(self, x: torch.Tensor) -> torch.Tensor:
        """The ``inferred`` classifier's softmax (N x K) for images ``x`` in [-1, 1] (no gradient)."""
        model = self.classifier.to(x.device).eval()
        images = ((x[:, :3].float() + 1.0) * 127.5).round().clamp(0, 255)
        side = self.classifier_settings["size"]
        if images.shape[-1] != side:
            images = F.interpolate(images, size=(side, side), mode="area").round()
        return torch.softmax(model(images.to(torch.uint8)).float(), dim=1)

    def record(self) -> dict:
        """What a model file stores (tensors stay tensors)."""
        classifier = None if self.classifier is None else {"settings": dict(self.classifier_settings),
                                                            "state_dict": self.classifier.state_dict()}
        return {"kind": self.kind, "classes": list(self.classes), "references": self.references,
                "classifier": classifier}

    @classmethod
    def from_record(cls, record: dict | None) -> "Conditioning":
        """Inverse of :meth:`record`; None (model files from before conditioning existed) is ``none``."""
        if record is None:
            return cls()
        saved, model, settings = record.get("classifier"), None, None
        if saved is not None:
            settings = dict(saved["settings"])
            model = (FeatureReader(len(record["classes"])) if settings.get("reader") == "features"
                     else make_classifier(len(record["classes"]), settings, 0))
            model.load_state_dict(saved["state_dict"])
            model.eval()
        return cls(record["kind"], tuple(record["classes"]), record.get("references"), model, settings)


def typical_images(images: torch.Tensor, classes: list[str], names: tuple[str, ...]) -> torch.Tensor:
    """One image per class of ``names``: the image of that class whose mean colour is nearest the median
    of its class's mean colours (a typical look, not an outlier). ``images`` is uint8 N x 3 x S x S with
    ``classes[i]`` the class of image i; every name needs at least one image."""
    means = images.float().mean(dim=(2, 3))
    chosen = []
    for name in names:
        rows = torch.tensor([i for i, c in enumerate(classes) if c == name], dtype=torch.int64)
        if not len(rows):
            raise ValueError(f"no image of class '{name}' to take a reference from")
        centre = means[rows].median(dim=0).values
        chosen.append(int(rows[(means[rows] - centre).norm(dim=1).argmin()]))
    return images[chosen].clone()
