"""Texture classifier: an AlexNet-style CNN and its training loop (pure torch, no file layout).

:class:`AlexNet` keeps Krizhevsky et al. (2012)'s shape - five convolutions (96, 256, 384,
384, 256 channels, times ``width``), overlapping 3x3/2 max-pooling after conv 1, 2 and 5, then
dropout and three linear layers ``fc6``, ``fc7`` (4096 x ``width`` units) and ``fc8`` - with
two changes for training from scratch on small tiles:

* BatchNorm after every convolution in place of local response normalisation, so a network
  trained from random weights with Adam converges within the paper's 10 epochs; after each
  epoch its running statistics are recomputed from up to 256 training images under the final
  weights (:func:`refresh_norm_statistics`), since the usual moving average lags far behind
  on epochs of a few dozen batches and made early test accuracies sit at chance;
* the first convolution follows the input side: 11x11 stride 4 (the original) from 160 px,
  5x5 stride 2 from 64 px, 3x3 stride 1 below, so the feature map never vanishes; an adaptive
  average pool then brings it to ``min(6, side)`` squared (6 x 6 at 227 px, as in AlexNet).

Networks take raw uint8 ``N x 3 x H x W`` tiles and scale them to [-1, 1] themselves.
:func:`train_classifier` trains one from a seed and records test accuracy after every epoch;
:func:`apply_weights` starts from a user's state_dict with only the last linear layers trained.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

BASE_CHANNELS = (96, 256, 384, 384, 256)
BASE_HIDDEN = 4096
MIN_CHANNELS = 8
MIN_SIZE = 32
LINEAR_LAYERS = ("fc6", "fc7", "fc8")  # classifier.<name>; "the last N linear layers" counts back from fc8
EVAL_BATCH = 256
NORM_IMAGES = 256  # training images (a fresh random draw each epoch) that set the batch-norm statistics
# train_classifier scales its training images (and their mirror images) once per run when they take at most
# this many bytes as float32, and per batch otherwise (the same numbers; this only bounds the memory)
PRESCALE_BYTES = 1 << 30
_TEST = object()  # key of the test set among train_classifier's evaluated sets (no extra set's name can equal it)


def first_conv(size: int) -> tuple[int, int, int]:
    """``(kernel, stride, padding)`` of conv 1 for input side ``size``: AlexNet's 11/4 from 160 px, 5/2 from 64, 3/1 below."""
    if size >= 160:
        return 11, 4, 2
    if size >= 64:
        return 5, 2, 2
    return 3, 1, 1


def feature_side(size: int) -> int:
    """Side of the map that conv 5's pooling leaves for a ``size`` x ``size`` input."""
    kernel, stride, padding = first_conv(size)
    side = (size + 2 * padding - kernel) // stride + 1
    for _ in range(3):  # max-pools 3x3 stride 2 after conv 1, 2 and 5; the other convs keep the side
        side = (side - 3) // 2 + 1
    return side


def scale_images(images: torch.Tensor) -> torch.Tensor:
    """uint8 tiles -> float in [-1, 1], channels-last in memory (about 1.5x faster convolutions on CPU)."""
    if images.dtype != torch.uint8:
        raise ValueError(f"the classifier takes uint8 images (raw tiles), got {images.dtype}")
    return (images.float() / 127.5 - 1.0).contiguous(memory_format=torch.channels_last)


class AlexNet(nn.Module):
    """AlexNet-style classifier of uint8 ``N x 3 x size x size`` tiles into ``num_classes`` logits.

    ``width`` scales every conv's channels (at least 8) and the hidden units of fc6 and fc7;
    ``batch_norm`` False gives the plain conv + ReLU stack (with conv biases) of the original.
    """

    def __init__(self, num_classes: int, size: int = 64, width: float = 0.25, batch_norm: bool = True,
                 dropout: float = 0.5):
        super().__init__()
        if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 2:
            raise ValueError(f"a classifier needs at least 2 classes, got {num_classes!r}")
        if isinstance(size, bool) or not isinstance(size, int) or size < MIN_SIZE:
            raise ValueError(f"input size must be an integer >= {MIN_SIZE}, got {size!r}")
        if not width > 0:
            raise ValueError(f"width must be > 0, got {width!r}")
        self.num_classes, self.size, self.width = num_classes, size, width
        channels = [max(MIN_CHANNELS, round(c * width)) for c in BASE_CHANNELS]
        hidden = max(MIN_CHANNELS, round(BASE_HIDDEN * width))
        kernel, stride, padding = first_conv(size)
        shapes = [(3, channels[0], kernel, stride, padding), (channels[0], channels[1], 5, 1, 2),
                  (channels[1], channels[2], 3, 1, 1), (channels[2], channels[3], 3, 1, 1),
                  (channels[3], channels[4], 3, 1, 1)]
        layers: list[tuple[str, nn.Module]] = []
        for i, (c_in, c_out, k, s, p) in enumerate(shapes, start=1):
            layers.append((f"conv{i}", nn.Conv2d(c_in, c_out, k, s, p, bias=not batch_norm)))
            if batch_norm:
                layers.append((f"norm{i}", nn.BatchNorm2d(c_out)))
            layers.append((f"relu{i}", nn.ReLU(inplace=True)))
            if i in (1, 2, 5):
                layers.append((f"pool{i}", nn.MaxPool2d(3, 2)))
        self.features = nn.Sequential(OrderedDict(layers))
        self.pooled_side = min(6, feature_side(size))
        self.avgpool = nn.AdaptiveAvgPool2d(self.pooled_side)
        self.classifier = nn.Sequential(OrderedDict([
            ("drop6", nn.Dropout(dropout)), ("fc6", nn.Linear(channels[4] * self.pooled_side ** 2, hidden)),
            ("relu6", nn.ReLU(inplace=True)),
            ("drop7", nn.Dropout(dropout)), ("fc7", nn.Linear(hidden, hidden)), ("relu7", nn.ReLU(inplace=True)),
            ("fc8", nn.Linear(hidden, num_classes)),
        ]))
        self.to(memory_format=torch.channels_last)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 N x 3 x H x W -> float logits N x num_classes."""
        return self.scaled_forward(scale_images(images))

    def scaled_forward(self, scaled: torch.Tensor) -> torch.Tensor:
        """Logits of tiles already through :func:`scale_images` (float in [-1, 1], channels-last): the
        training loop scales its sets once rather than every batch, and gets the same numbers."""
        return self.classifier(torch.flatten(self.avgpool(self.features(scaled)), 1))


def make_classifier(num_classes: int, settings: Mapping, seed: int) -> AlexNet:
    """The network ``train_classifier`` starts from: AlexNet(size, width of ``settings``) initialised from ``seed``."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return AlexNet(num_classes, settings["size"], settings["width"])


def apply_weights(model: AlexNet, state: Mapping, retrain_layers: int, source: str = "weights") -> dict:
    """Load ``state`` (a state_dict of this architecture, read from ``source``) into ``model`` and leave
    only its last ``retrain_layers`` linear layers trainable. An fc8 for another number of classes is not loaded: the model keeps its own
    freshly initialised fc8. Any other missing, extra or differently shaped entry is a ValueError
    naming the first such key. Returns ``{"reinitialised": [...], "trainable": [...]}``.
    """
    if isinstance(retrain_layers, bool) or retrain_layers not in range(1, len(LINEAR_LAYERS) + 1):
        raise ValueError(f"retrain_layers must be 1 to {len(LINEAR_LAYERS)}, got {retrain_layers!r}")
    own = model.state_dict()
    missing = [key for key in own if key not in state]
    if missing:
        raise ValueError(f"{source}: key {missing[0]} is missing from the file ({len(missing)} missing); "
                         f"it does not hold this architecture")
    extra = [key for key in state if key not in own]
    if extra:
        raise ValueError(f"{source}: key {extra[0]} in the file is not in the model ({len(extra)} extra); "
                         f"it does not hold this architecture")
    merged, reinitialised = dict(own), []
    last = f"classifier.{LINEAR_LAYERS[-1]}."
    for key, tensor in own.items():
        given = state[key]
        if given.shape == tensor.shape:
            merged[key] = given.to(tensor.dtype)
        elif key.startswith(last) and given.shape[1:] == tensor.shape[1:]:
            reinitialised.append(key)  # another number of classes: keep the model's own fresh fc8
        else:
            raise ValueError(f"{source}: key {key} has shape {tuple(given.shape)} in the file but "
                             f"{tuple(tensor.shape)} in the model (check classify.size and classify.width)")
    model.load_state_dict(merged)
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    trainable = list(LINEAR_LAYERS[-retrain_layers:])
    for name in trainable:
        for parameter in getattr(model.classifier, name).parameters():
            parameter.requires_grad_(True)
    return {"reinitialised": reinitialised, "trainable": trainable}


class TrainingDiverged(RuntimeError):
    """The mean training loss of an epoch became non-finite (NaN or infinite); ``epoch``, ``seed``, ``loss`` say where."""

    def __init__(self, epoch: int, seed: int, loss: float):
        super().__init__(f"classifier training diverged: mean loss {loss} in epoch {epoch} (seed {seed}); lower classify.lr")
        self.epoch, self.seed, self.loss = epoch, seed, loss


def wilson_interval(accuracy: float, count: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval (95% for z = 1.96) of a proportion ``accuracy`` observed on ``count`` trials;
    ``(0, 1)`` when ``count`` is 0."""
    if count <= 0:
        return 0.0, 1.0
    share = min(max(float(accuracy), 0.0), 1.0)
    factor = 1 + z * z / count
    centre = (share + z * z / (2 * count)) / factor
    half = z / factor * math.sqrt(share * (1 - share) / count + z * z / (4 * count * count))
    # rounding can put a bound one ulp inside the observed share at 0 or 1; the interval always holds it
    return max(0.0, min(centre - half, share)), min(1.0, max(centre + half, share))


def at_chance(accuracy: float, count: int, num_classes: int) -> bool:
    """True when ``accuracy`` on ``count`` test images is not distinguishable from chance ``1 / num_classes``:
    chance lies inside the 95% Wilson interval of the accuracy. False when nothing was measured
    (``count`` 0 or a NaN accuracy)."""
    if count <= 0 or accuracy is None or not math.isfinite(accuracy):
        return False
    low, high = wilson_interval(accuracy, count)
    return low <= 1.0 / num_classes <= high


@dataclass
class ClassifierRun:
    """One training run: per-epoch test accuracy, accuracy on each extra set, mean train loss; the trained model."""

    test_accuracy: list[float]
    extra_accuracy: dict[str, list[float]]
    train_loss: list[float]
    seconds: float
    model: AlexNet
    weights: dict | None = field(default=None)
    # final-epoch arg-max classes of the test set and of each extra set (the last evaluation, kept so that
    # callers need not classify the same images again)
    test_predictions: torch.Tensor | None = field(default=None)
    extra_predictions: dict[str, torch.Tensor] = field(default_factory=dict)
    # where ``seconds`` went: mini-batch training (``train_images`` image visits, all epochs), the per-epoch
    # batch-norm refresh, and evaluation (``eval_images`` images classified, all epochs and sets)
    train_seconds: float = 0.0
    train_images: int = 0
    norm_seconds: float = 0.0
    eval_seconds: float = 0.0
    eval_images: int = 0


@torch.no_grad()
def predict(model: nn.Module, images: torch.Tensor, batch_size: int = EVAL_BATCH) -> torch.Tensor:
    """Arg-max class of each of ``images`` (int64, on the CPU), in eval mode; empty for an empty set."""
    if len(images) == 0:
        return torch.empty(0, dtype=torch.long)
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    labels = [model(images[start:start + batch_size].to(device)).argmax(dim=1).cpu()
              for start in range(0, len(images), batch_size)]
    model.train(was_training)
    return torch.cat(labels)


@torch.no_grad()
def accuracy(model: nn.Module, images: torch.Tensor, labels: torch.Tensor, batch_size: int = EVAL_BATCH) -> float:
    """Share of ``images`` whose arg-max logit is the label, in eval mode; NaN for an empty set."""
    if len(images) == 0:
        return math.nan
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    correct = 0
    for start in range(0, len(images), batch_size):
        logits = model(images[start:start + batch_size].to(device))
        correct += int((logits.argmax(dim=1).cpu() == labels[start:start + batch_size].cpu()).sum())
    model.train(was_training)
    return correct / len(images)


@torch.inference_mode()
def _predict_classes(model: AlexNet, images: torch.Tensor, scaled: bool, batch_size: int = EVAL_BATCH) -> torch.Tensor:
    """Arg-max classes of ``images`` (uint8 tiles, or tiles already through :func:`scale_images` with
    ``scaled``: the same numbers), in eval mode, batched as :func:`predict`; int64 on the images' device."""
    was_training = model.training
    model.eval()
    labels = [(model.scaled_forward(batch) if scaled else model(batch)).argmax(dim=1)
              for batch in (images[start:start + batch_size] for start in range(0, len(images), batch_size))]
    model.train(was_training)
    return torch.cat(labels) if labels else torch.empty(0, dtype=torch.long, device=images.device)


@torch.inference_mode()
def class_probabilities(model: AlexNet, images: torch.Tensor, batch_size: int = EVAL_BATCH) -> torch.Tensor:
    """Softmax class probabilities (``N x classes``, float32 on the CPU) of uint8 ``images``, in eval mode."""
    was_training = model.training
    model.eval()
    device = next(model.parameters()).device
    parts = [torch.softmax(model(images[start:start + batch_size].to(device)).float(), dim=1).cpu()
             for start in range(0, len(images), batch_size)]
    model.train(was_training)
    return torch.cat(parts) if parts else torch.empty(0, model.num_classes)


def _check_set(name: str, images: torch.Tensor, labels: torch.Tensor, num_classes: int, size: int) -> None:
    if not isinstance(images, torch.Tensor) or images.dtype != torch.uint8 or images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"{name}: expected uint8 images N x 3 x H x W, got "
                         f"{getattr(images, 'dtype', type(images).__name__)} {tuple(getattr(images, 'shape', ()))}")
    if images.shape[-2:] != (size, size):
        raise ValueError(f"{name}: images are {images.shape[-1]}x{images.shape[-2]}, the classifier takes {size}x{size}")
    if labels.ndim != 1 or len(labels) != len(images):
        raise ValueError(f"{name}: {len(images)} images but labels of shape {tuple(labels.shape)}")
    if len(labels) and (int(labels.min()) < 0 or int(labels.max()) >= num_classes):
        raise ValueError(f"{name}: labels must lie in [0, {num_classes - 1}], got [{int(labels.min())}, {int(labels.max())}]")


def _hold_frozen_norms(model: nn.Module) -> None:
    """Batch-norm layers whose parameters are frozen keep their running statistics (eval mode)."""
    for module in model.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm) and not any(p.requires_grad for p in module.parameters()):
            module.eval()


@torch.no_grad()
def refresh_norm_statistics(model: AlexNet, images: torch.Tensor, batch_size: int = EVAL_BATCH,
                            scaled: bool = False) -> None:
    """Set every trainable batch-norm layer's running mean and variance to their average over ``images``
    (uint8 tiles, or tiles already through :func:`scale_images` with ``scaled``) under the current
    weights ("precise BN"), so evaluation does not use statistics that lag behind. The layers after
    the last such norm do not change them and are not run."""
    norms = [m for m in model.features.modules()
             if isinstance(m, nn.modules.batchnorm._BatchNorm) and any(p.requires_grad for p in m.parameters())]
    if not norms or len(images) == 0:
        return
    device = next(model.parameters()).device
    layers = list(model.features.children())
    last = [i for i, m in enumerate(layers) if m is norms[-1]]
    upto = nn.Sequential(*layers[:last[0] + 1]) if last else model.features
    was_training, momenta = model.training, [m.momentum for m in norms]
    for module in norms:
        module.reset_running_stats()
        module.momentum = None  # cumulative average over the batches below
        module.train()
    for start in range(0, len(images), batch_size):
        batch = images[start:start + batch_size].to(device)
        upto(batch if scaled else scale_images(batch))
    for module, momentum in zip(norms, momenta):
        module.momentum = momentum
    model.train(was_training)


class _TrainingImages:
    """The training set as mini-batches are drawn from it (knows scaling and mirroring).

    Each set is scaled once rather than per batch and epoch when the scaled images and their mirror
    images fit PRESCALE_BYTES. Scaling and mirroring are exact, so a batch gathered from ``bank`` (the
    scaled images, then their mirror images) equals, bit for bit, the batch mirrored and scaled on
    the fly as the fallback does.
    """

    def __init__(self, images: torch.Tensor, labels: torch.Tensor, flip: bool, device: torch.device):
        self.count, self.flip = len(images), flip
        self.prescale = (2 if flip else 1) * images.numel() * 4 <= PRESCALE_BYTES
        self.images, self.labels = images.to(device), labels.long().to(device)
        self.bank = None
        if self.prescale:
            self.images = scale_images(self.images)
            if flip:
                self.bank = torch.cat([self.images, self.images.flip(-1)]).contiguous(memory_format=torch.channels_last)
                self.images = self.bank[:self.count]  # a view: the unmirrored half, for the batch-norm refresh
            else:
                self.bank = self.images

    def prepare(self, images: torch.Tensor, device: torch.device) -> torch.Tensor:
        """An evaluation set in the form the model is run on here (scaled once when prescaling)."""
        return scale_images(images.to(device)) if self.prescale else images.to(device)

    def batch(self, order: torch.Tensor, mirrored: torch.Tensor, start: int, size: int) -> torch.Tensor:
        """Scaled images ``order[start:start + size]``, each mirrored where ``mirrored`` (indexed by image) says."""
        index = order[start:start + size]
        if self.prescale:
            # row of each image in ``bank``: that of its mirror image (count to 2 count - 1) where drawn mirrored
            return self.bank[index + self.count * mirrored[index].long() if self.flip else index]
        x = self.images[index]
        if self.flip:
            x = torch.where(mirrored[index].view(-1, 1, 1, 1), x.flip(-1), x)
        return scale_images(x)


def _autocast(device: torch.device, precision: str):
    """bf16 autocast for ``precision`` bf16, else a no-op context (fp32)."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")


def _train_epoch(model: AlexNet, optimiser, data: _TrainingImages, sampler: torch.Generator, batch_size: int,
                 precision: str, visits: int | None = None) -> tuple[float, torch.Tensor]:
    """``visits`` image visits (None: ``data.count``, one pass) in mini-batches, as consecutive seeded shuffled
    passes over ``data``, the last one cut short; a fresh order and mirroring per pass. Returns the mean loss
    and the first pass's order. One whole pass draws exactly what a plain shuffled epoch draws."""
    device = data.labels.device
    remaining = data.count if visits is None else visits
    total, first = torch.zeros((), device=device), None
    while remaining > 0:
        order = torch.randperm(data.count, generator=sampler)
        mirrored = torch.rand(data.count, generator=sampler) < 0.5
        order, mirrored = order.to(device), mirrored.to(device)
        first = order if first is None else first
        used = min(remaining, data.count)
        for start in range(0, used, batch_size):
            size = min(batch_size, used - start)
            with _autocast(device, precision):
                logits = model.scaled_forward(data.batch(order, mirrored, start, size))
            loss = F.cross_entropy(logits.float(), data.labels[order[start:start + size]])
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            total += loss.detach() * size
        remaining -= used
    return float(total) / (data.count if visits is None else visits), first


class EarlyStopping:
    """Stop after ``patience`` epochs without a new best validation accuracy (0: never stop early).

    The model kept is the last epoch's (no rollback), so the accuracy table's last row per run stays
    the run's final accuracy."""

    def __init__(self, patience: int):
        self.patience, self.best, self.best_epoch = patience, -math.inf, 0

    def should_stop(self, epoch: int, val_accuracy: float) -> bool:
        """Record ``val_accuracy`` of ``epoch``; True when training should end after it."""
        if not self.patience or not math.isfinite(val_accuracy):
            return False
        if val_accuracy > self.best:
            self.best, self.best_epoch = val_accuracy, epoch
        return epoch - self.best_epoch >= self.patience


def _checked_sets(train_x, train_y, test_x, test_y, num_classes, size, extra_eval, val, precision) -> dict:
    """Validate train_classifier's arguments (ValueError naming the set); return the extra sets to evaluate,
    the validation set among them as ``"val"``."""
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 2:
        raise ValueError(f"classification needs at least 2 classes, got {num_classes!r}")
    if len(train_x) == 0:
        raise ValueError("the training set is empty")
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision must be fp32 or bf16, got {precision!r}")
    _check_set("training set", train_x, train_y, num_classes, size)
    _check_set("test set", test_x, test_y, num_classes, size)
    extra_eval = dict(extra_eval or {})
    if val is not None and len(val[0]):
        if "val" in extra_eval:
            raise ValueError("extra_eval may not name a set 'val' when a validation set is given")
        extra_eval["val"] = val
    for name, (x, y) in extra_eval.items():
        _check_set(f"evaluation set {name!r}", x, y, num_classes, size)
    return extra_eval


def _evaluate(model: AlexNet, evaluated: dict, scaled: bool, precision: str, run: ClassifierRun,
              predictions: dict) -> None:
    """Classify every evaluated set (the test set under ``_TEST``); append each accuracy to ``run`` and keep the
    predicted classes in ``predictions``."""
    device = next(model.parameters()).device
    for name, (x, y) in evaluated.items():
        with _autocast(device, precision):
            predictions[name] = _predict_classes(model, x, scaled=scaled)
        share = int((predictions[name] == y).sum()) / len(y) if len(y) else math.nan
        (run.test_accuracy if name is _TEST else run.extra_accuracy[name]).append(share)
        run.eval_images += len(y)


def _lr_schedule(optimiser, name: str, epochs: int):
    """``constant`` (None: the optimiser's rate throughout) or ``cosine``: the rate of epoch ``e`` (1-based) is
    ``lr * (1 + cos(pi * (e - 1) / epochs)) / 2`` (Loshchilov & Hutter 2017, without restarts), stepped per epoch."""
    if name == "constant":
        return None
    if name != "cosine":
        raise ValueError(f"lr_schedule must be constant or cosine, got {name!r}")
    return torch.optim.lr_scheduler.LambdaLR(optimiser, lambda done: (1 + math.cos(math.pi * done / epochs)) / 2)


def _average_epochs(settings: Mapping, epochs: int) -> int:
    """How many final epochs' weights are averaged (``average_epochs``, default 0 = none), at most ``epochs``."""
    count = settings.get("average_epochs", 0)
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise ValueError(f"average_epochs must be a whole number >= 0, got {count!r}")
    return min(count, epochs)


def train_classifier(train_x: torch.Tensor, train_y: torch.Tensor, test_x: torch.Tensor, test_y: torch.Tensor,
                     num_classes: int, settings: Mapping, seed: int, device: str | torch.device = "cpu",
                     extra_eval: Mapping[str, tuple[torch.Tensor, torch.Tensor]] | None = None,
                     weights: Mapping | None = None, retrain_layers: int = 2, weights_source: str = "weights",
                     progress: Callable[[int, dict], None] | None = None,
                     val: tuple[torch.Tensor, torch.Tensor] | None = None, precision: str = "fp32",
                     epoch_images: int | None = None) -> ClassifierRun:
    """Train :func:`make_classifier` (``settings``: size, width, epochs, batch_size, lr; optional flip, default
    True, patience, default 0, lr_schedule, default constant (:func:`_lr_schedule`), and average_epochs,
    default 0 (:func:`_average_epochs`)).

    Images are uint8 ``N x 3 x size x size``, labels integers in ``[0, num_classes)``. Each epoch
    visits the training set once in a seeded shuffled order, in mini-batches (the last one may be
    smaller), with Adam at ``lr`` on cross-entropy; with ``flip`` each image is mirrored left-right
    with probability 1/2. With ``epoch_images`` an epoch is that many image visits instead (consecutive
    shuffled passes, the last cut short), so that runs on sets of different sizes take equal steps.
    After every epoch the model is evaluated (eval mode, no grad) on the test set, on each
    ``extra_eval`` set and on ``val``, and ``progress(epoch, row)`` is called. With average_epochs N the model
    evaluated from epoch ``epochs - N + 1`` on, and returned, is the running mean of the weights after each of
    those epochs (stochastic weight averaging; its batch-norm statistics recomputed), while training goes on
    from the unaveraged weights.
    With a non-empty ``val`` and ``patience`` > 0, training ends once ``patience`` epochs passed
    without a new best validation accuracy (:class:`EarlyStopping`); otherwise it runs ``epochs``.
    ``precision`` bf16 runs forward passes under bf16 autocast (fp32: none). Everything random derives
    from ``seed`` (the caller's global RNG state is left untouched), so on CPU the same seed gives
    identical accuracies. ``weights`` (a state_dict read from ``weights_source``) is applied with
    :func:`apply_weights`. A non-finite mean training loss in an epoch raises :class:`TrainingDiverged`
    at the end of that epoch. The run keeps the final epoch's predicted classes (the validation set's
    under the name ``"val"`` in ``extra_predictions``) and where its time went (``train_seconds`` for
    ``train_images`` image visits, ``eval_seconds`` for ``eval_images`` classified, ``norm_seconds``).
    """
    extra_eval = _checked_sets(train_x, train_y, test_x, test_y, num_classes, settings["size"], extra_eval, val,
                               precision)
    if epoch_images is not None and (isinstance(epoch_images, bool) or not isinstance(epoch_images, int)
                                     or epoch_images < 1):
        raise ValueError(f"epoch_images must be a positive number of image visits or None, got {epoch_images!r}")
    epochs, batch_size, device = settings["epochs"], settings["batch_size"], torch.device(device)

    model = make_classifier(num_classes, settings, seed)
    loaded = apply_weights(model, weights, retrain_layers, weights_source) if weights is not None else None
    model.to(device)
    optimiser = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=settings["lr"])
    started = time.perf_counter()
    data = _TrainingImages(train_x, train_y, bool(settings.get("flip", True)), device)
    evaluated = {name: (data.prepare(x, device), y.long().to(device))
                 for name, (x, y) in {_TEST: (test_x, test_y), **extra_eval}.items()}
    stopper = EarlyStopping(int(settings.get("patience", 0)) if "val" in extra_eval else 0)
    schedule = _lr_schedule(optimiser, settings.get("lr_schedule", "constant"), epochs)
    average_from = epochs - _average_epochs(settings, epochs) + 1  # first epoch in the weight average
    averaged = None
    sampler = torch.Generator().manual_seed(seed)
    run = ClassifierRun([], {name: [] for name in extra_eval}, [], 0.0, model, loaded)
    predictions: dict = {}
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(seed)  # dropout draws from the global generator
        for epoch in range(1, epochs + 1):
            epoch_started = time.perf_counter()
            model.train()
            _hold_frozen_norms(model)
            mean_loss, order = _train_epoch(model, optimiser, data, sampler, batch_size, precision, epoch_images)
            if not math.isfinite(mean_loss):
                raise TrainingDiverged(epoch, seed, mean_loss)
            if schedule is not None:
                schedule.step()
            run.train_loss.append(mean_loss)
            run.train_images += data.count if epoch_images is None else epoch_images
            norm_started = time.perf_counter()
            evaluated_model = model
            if epoch >= average_from:  # stochastic weight averaging: evaluate the mean of the weights so far
                if averaged is None:
                    averaged = torch.optim.swa_utils.AveragedModel(model)
                averaged.update_parameters(model)
                evaluated_model = averaged.module
            with _autocast(device, precision):
                refresh_norm_statistics(evaluated_model, data.images[order[:NORM_IMAGES]], scaled=data.prescale)
            eval_started = time.perf_counter()
            _evaluate(evaluated_model, evaluated, data.prescale, precision, run, predictions)
            done = time.perf_counter()
            run.train_seconds += norm_started - epoch_started
            run.norm_seconds += eval_started - norm_started
            run.eval_seconds += done - eval_started
            if progress:
                progress(epoch, {"train_loss": mean_loss, "test_accuracy": run.test_accuracy[-1],
                                 **{name: values[-1] for name, values in run.extra_accuracy.items()}})
            if stopper.should_stop(epoch, run.extra_accuracy["val"][-1] if "val" in extra_eval else math.nan):
                break
    model = averaged.module if averaged is not None else model
    model.eval()
    run.model, run.seconds = model.cpu(), time.perf_counter() - started
    run.test_predictions = predictions[_TEST].cpu() if predictions else None
    run.extra_predictions = {name: predictions[name].cpu() for name in extra_eval if predictions}
    return run
