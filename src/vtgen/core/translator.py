"""One conditional GAN under training: generator, discriminator, their optimisers and one training step.

:class:`TranslatorTraining` is one iteration of one of two objectives and nothing else: no data, no files,
no logging. The train stage (:mod:`vtgen.stages.train`) loops around it.

* ``pix2pix`` (Isola et al. 2017): for pixel- or name-paired data, where the target belongs to the input.
* ``class_gan``: for class-paired data, where the target is a random image of the input's class and a pixel
  loss towards it has the class mean as its optimum (the collapse measured in issue 24). No pixel loss; a
  projection discriminator told the class (Miyato & Koyama 2018) judges augmented images (DiffAugment, Zhao
  et al. 2020) with an R1 penalty (Mescheder et al. 2018); a clipped mode-seeking term (Mao et al. 2019;
  Yang et al. 2019) makes outputs of two inputs of one class differ as much as two real images of it do.
"""

from __future__ import annotations

import contextlib
import copy

import torch
import torch.nn.functional as F
from torch import nn

from vtgen.core.augment import augment_policy, diff_augment
from vtgen.core.spectrum import rgb_log_radial_profiles
from vtgen.core.gan import adversarial_loss, make_optimizer
from vtgen.core.models import build_discriminator, build_generator, conditional_pair, ProjectionDiscriminator
from vtgen.core.patchnce import patch_nce_loss, PatchProjection
from vtgen.core.texture import contextual_loss, RandomFilterBank, texture_loss

LOSS_NAMES = ("loss_d", "loss_g_gan", "loss_g_l1")
STATE_KEYS = ("generator", "discriminator", "opt_g", "opt_d")
PRECISIONS = ("fp32", "bf16")
OBJECTIVES = ("pix2pix", "class_gan")
MODE_SEEKING_EPS = 1e-5  # floor of the real gap in the mode-seeking ratio
FIXED_PATTERN_EPS = 1e-12  # floor of the squared mean fine-detail energy in the detail concentration
FIXED_SIGN_DECAY = 0.99  # decay of the running mean of the outputs' fine detail that ``fixed_sign`` charges (about 100 batches)
NCE_LEVELS = (0, 1, 2)  # generator encoder levels PatchNCE compares (at 64 px: 32, 16 and 8 px maps)


def recognition_loss(guide: nn.Module, images: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """CE(guide(images), labels), averaged over the batch: the cross-entropy of a frozen classifier of the
    target modality (:class:`vtgen.core.classifier.AlexNet`, eval mode) on ``images`` (N x 3 x S x S floats in
    [-1, 1], the generator's range, area-resized to the guide's side), differentiable in ``images`` (the
    semantic consistency term of CyCADA, Hoffman et al. 2018, eq. 4, with the known class as its target)."""
    side = guide.size
    if images.shape[-1] != side:
        images = F.interpolate(images, size=(side, side), mode="area")
    logits = guide.scaled_forward(images.contiguous(memory_format=torch.channels_last))
    return F.cross_entropy(logits.float(), labels)


def discriminator_features(discriminator: nn.Module, pair: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """``discriminator(pair)`` and the output of each of its LeakyReLU layers, in order: the
    intermediate features that feature matching compares (pix2pixHD, Wang et al. 2018)."""
    features: list[torch.Tensor] = []
    hooks = [module.register_forward_hook(lambda _module, _inputs, output: features.append(output))
             for module in discriminator.modules() if isinstance(module, nn.LeakyReLU)]
    try:
        logits = discriminator(pair)
    finally:
        for hook in hooks:
            hook.remove()
    return logits, features


class TranslatorTraining:
    """G, D and their optimisers, built from a presets block (size, ngf, ndf, kernel, discriminator,
    patch_layers, gan_loss, l1_weight, optimizer, lr, betas, and the optional feature_matching and
    spectrum_matching weights, 0 when absent; other keys are ignored).

    Weights are drawn from torch's global generator: seed it first for a reproducible start.
    Optimisers take their multi-tensor step (fused Adam, foreach RMSprop); ``precision`` 'bf16'
    runs the forward passes under bf16 autocast (weights, losses and optimiser state stay fp32).
    ``input_channels`` is the generator's input: the 3 image channels plus those of a
    :class:`vtgen.core.conditioning.Conditioning`; the discriminator sees those and the 3 of the image judged.
    ``settings['objective']`` (default 'pix2pix') picks the step; 'class_gan' also reads ``r1``,
    ``diffaugment``, ``mode_seeking``, ``mode_seeking_pool``, ``mode_seeking_per_pair``, ``pack``, ``statistics``, ``statistics_spectrum``, ``statistics_pool``, ``fixed_pattern``, ``fixed_sign``, ``shared_detail``, ``class_guidance``, ``skips``,
    ``latent``, ``upsample``, ``padding``, ``semantic``, ``mismatch``, ``nce``, ``texture``, ``contextual`` (see :meth:`class_step`), ``d_lr_ratio`` (D's learning rate over
    G's), ``ema`` (:meth:`update_average`: the generator a run yields is the average of its weights), ``lr_decay``
    (:meth:`schedule_learning_rate`) and ``generator`` (:func:`vtgen.core.models.build_generator`: unet, the default, or resnet), and needs ``num_classes``; ``semantic`` > 0 needs ``guide``, a classifier of the target modality over the
    same class indices (frozen here: eval mode, no gradients for its weights).
    """

    def __init__(self, settings: dict, device: torch.device | str = "cpu", precision: str = "fp32",
                 input_channels: int = 3, num_classes: int = 0, guide: nn.Module | None = None) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"unknown precision '{precision}' (allowed: {', '.join(PRECISIONS)})")
        self.objective = settings.get("objective", "pix2pix")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"unknown objective '{self.objective}' (allowed: {', '.join(OBJECTIVES)})")
        self.settings, self.device, self.precision = settings, torch.device(device), precision
        size, kernel = settings["size"], settings["kernel"]
        self.generator = build_generator(settings, input_channels).to(self.device).train()
        if self.objective == "class_gan":
            self.pack = int(settings.get("pack", 1))
            if self.pack not in (1, 2):
                raise ValueError(f"class_gan.pack must be 1 or 2 (the rows of a batch come in pairs of a class), got {self.pack}")
            self.discriminator = ProjectionDiscriminator(
                num_classes, settings["ndf"], settings["patch_layers"], kernel, in_channels=3 * self.pack,
                class_head=bool(settings.get("class_guidance", 0.0)),
                antialias=bool(settings.get("d_antialias", False))).to(self.device).train()
        else:
            self.discriminator = build_discriminator(settings["discriminator"], size, settings["ndf"], kernel,
                                                     settings["patch_layers"], input_channels + 3).to(self.device).train()
        if self.objective == "class_gan" and settings.get("mismatch", 0.0) and num_classes < 2:
            raise ValueError(f"class_gan.mismatch shows real images under a wrong class: it needs at least 2 classes, "
                             f"got {num_classes}: set translation.class_gan.mismatch to 0 for a one-class scope")
        self.guide = None
        if self.objective == "class_gan" and settings.get("semantic", 0.0):
            if guide is None:
                raise ValueError("class_gan.semantic > 0 needs a classifier of the target modality (the guide)")
            self.guide = guide.to(self.device).eval().requires_grad_(False)
        # class_gan's nce: the projection heads of PatchNCE, trained with the generator by its optimiser
        self.nce_levels = tuple(level for level in NCE_LEVELS if level < self.generator.feature_levels)
        self.nce_projection = None
        if self.objective == "class_gan" and settings.get("nce", 0.0):
            self.nce_projection = PatchProjection([self.generator.feature_width(level) for level in self.nce_levels]
                                                  ).to(self.device).train()
        # class_gan's texture and contextual terms: the fixed random filter bank whose features compare an output with a real image
        self.texture_bank = (RandomFilterBank().to(self.device) if self.objective == "class_gan"
                             and (settings.get("texture", 0.0) or settings.get("contextual", 0.0)) else None)
        # class_gan's ema: an exponential moving average of G's weights, the generator the run yields
        self.ema_decay = float(settings.get("ema", 0.0)) if self.objective == "class_gan" else 0.0
        self.average, self.average_updates = None, 0
        if self.ema_decay:
            self.average = copy.deepcopy(self.generator).requires_grad_(False)
        # class_gan's fixed_sign: the running mean of the outputs' fine detail (C x H x W), and its update count
        self.detail_mean, self.detail_updates = None, 0
        g_parameters = list(self.generator.parameters())
        if self.nce_projection is not None:
            g_parameters += list(self.nce_projection.parameters())
        # class_gan's d_lr_ratio: D's learning rate over G's (two time-scale update rule, Heusel et al. 2017)
        d_ratio = settings.get("d_lr_ratio", 1.0) if self.objective == "class_gan" else 1.0
        self.base_lrs = (settings["lr"], settings["lr"] * d_ratio)
        self.opt_g, self.opt_d = (make_optimizer(parameters, settings["optimizer"], lr, settings["betas"],
                                                 multi_tensor_on=self.device.type)
                                  for parameters, lr in zip((g_parameters, self.discriminator.parameters()), self.base_lrs))
        # class_gan's lr_decay: the share of the steps, at the end, over which both learning rates fall to 0
        self.lr_decay = float(settings.get("lr_decay", 0.0)) if self.objective == "class_gan" else 0.0

    def schedule_learning_rate(self, step: int, iterations: int) -> None:
        """Set both learning rates for step ``step`` (from 0) of ``iterations``: with ``lr_decay`` = f > 0,
        lr_t = lr · min(1, (T − t) / (f·T)), constant and then falling linearly towards 0 over the last f·T steps
        (the schedule of pix2pix and CycleGAN, Isola et al. 2017, Zhu et al. 2017); D's keeps its ``d_lr_ratio``.
        A function of t alone, so a resumed run continues the same schedule. f = 0 leaves the rates untouched."""
        if not self.lr_decay:
            return
        scale = min(1.0, (iterations - step) / (self.lr_decay * iterations))
        for optimizer, base in zip((self.opt_g, self.opt_d), self.base_lrs):
            for group in optimizer.param_groups:
                group["lr"] = base * scale

    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _loss(self, logits: torch.Tensor, real: bool) -> torch.Tensor:
        return adversarial_loss(logits, real, self.settings["gan_loss"])

    def step(self, x: torch.Tensor, y: torch.Tensor, labels: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """One iteration of the objective: :meth:`class_step` for 'class_gan' (``labels`` needed), else
        :meth:`pix2pix_step`."""
        if self.objective == "class_gan":
            if labels is None:
                raise ValueError("the class_gan objective needs the class index of every batch row")
            return self.class_step(x, y, labels)
        return self.pix2pix_step(x, y)

    def pix2pix_step(self, x: torch.Tensor, y: torch.Tensor) -> dict[str, torch.Tensor]:
        """One iteration on a batch (conditions ``x``, N x input_channels x S x S, and targets ``y``,
        N x 3 x S x S, in [-1, 1] on the device).

        D minimises ½[L(D(x, y), real) + L(D(x, G(x)), fake)]; then, with D's weights frozen,
        G minimises L(D(x, G(x)), real) + l1_weight·|G(x) − y|₁ (pix2pix eq. 4)
        + feature_matching·(1/K)Σₖ |Dₖ(x, G(x)) − Dₖ(x, y)|₁ over D's K LeakyReLU outputs, the real
        ones taken from D's own step (pix2pixHD eq. 4, Wang et al. 2018; off when the weight is 0)
        + spectrum_matching·|s(G(x)) − s(y)|₁, s the log10 radial power profile of each image's grey
        (:func:`vtgen.core.spectrum.log_radial_profiles`, the score stage's spectrum metric;
        spectral regularisation after Durall et al. 2020; off when the weight is 0).
        Returns the detached 0-d losses named by :data:`LOSS_NAMES` (no host sync).
        """
        matching = self.settings.get("feature_matching", 0.0)
        with self._autocast():
            fake = self.generator(x)
            if matching:
                d_real, real_features = discriminator_features(self.discriminator, conditional_pair(x, y))
                real_features = [f.detach() for f in real_features]
            else:
                d_real, real_features = self.discriminator(conditional_pair(x, y)), []
            d_fake = self.discriminator(conditional_pair(x, fake.detach()))
        loss_d = 0.5 * (self._loss(d_real, True) + self._loss(d_fake, False))
        self.opt_d.zero_grad(set_to_none=True)
        loss_d.backward()
        self.opt_d.step()
        loss_g_gan, loss_g_l1 = self._generator_step(x, y, fake, real_features)
        return dict(zip(LOSS_NAMES, (loss_d.detach(), loss_g_gan.detach(), loss_g_l1.detach())))

    def _generator_step(self, x: torch.Tensor, y: torch.Tensor, fake: torch.Tensor,
                        real_features: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """G's update; D is frozen meanwhile (gradients flow through it, none are computed for its weights)."""
        self.discriminator.requires_grad_(False)
        try:
            with self._autocast():
                if real_features:
                    d_fake, fake_features = discriminator_features(self.discriminator, conditional_pair(x, fake))
                else:
                    d_fake = self.discriminator(conditional_pair(x, fake))
            loss_g_gan = self._loss(d_fake, True)
            loss_g_l1 = F.l1_loss(fake.float(), y)
            weight = self.settings["l1_weight"]
            loss_g = loss_g_gan + weight * loss_g_l1 if weight else loss_g_gan
            if real_features:
                matched = sum(F.l1_loss(f.float(), r.float()) for f, r in zip(fake_features, real_features))
                loss_g = loss_g + self.settings["feature_matching"] * matched / len(real_features)
            spectral = self.settings.get("spectrum_matching", 0.0)
            if spectral:
                loss_g = loss_g + spectral * F.l1_loss(rgb_log_radial_profiles(fake.float()),
                                                   rgb_log_radial_profiles(y))
            self.opt_g.zero_grad(set_to_none=True)
            loss_g.backward()
            self.opt_g.step()
        finally:
            self.discriminator.requires_grad_(True)
        return loss_g_gan, loss_g_l1

    def class_step(self, x: torch.Tensor, y: torch.Tensor, labels: torch.Tensor) -> dict[str, torch.Tensor]:
        """One class-paired iteration. Rows ``2k`` and ``2k+1`` of the batch hold two inputs of one class
        (``labels``, N class indices; N even); ``y`` are real targets of those classes, not partners of ``x``.

        With A the DiffAugment of :func:`vtgen.core.augment.diff_augment` with the transforms ``diffaugment``
        names (:func:`vtgen.core.augment.augment_policy`: true = all, false = identity) and D(·, c) the
        projection discriminator:
        D minimises ½[L(D(A(y), c), real) + L(D(A(G(x)), c), fake)] + (r1/2)·E‖∇_y D(A(y), c)‖² (R1,
        Mescheder et al. 2018, on the real images; the gradient of each image's mean patch logit);
        then G minimises L(D(A(G(x)), c), real) + mode_seeking·max(0, 1 − r), with
        r = mean|G(x₂ₖ) − G(x₂ₖ₊₁)| / mean|y₂ₖ − y₂ₖ₊₁| (:func:`mode_seeking_loss`: Mao et al. 2019, eq. 3,
        with the second input of the class in place of a second noise draw, clipped as in DSGAN), the gaps
        taken between ``mode_seeking_pool`` x ``mode_seeking_pool`` means (1: pixels), the hinge per pair with
        ``mode_seeking_per_pair``.
        With ``statistics`` w > 0, G += w·:func:`statistics_loss` (G(x), y): colour, contrast and power spectrum
        of each output against those of the real image of its class in its row (``statistics_spectrum`` false: colour
        and contrast only; ``statistics_pool`` p > 1: contrast between p x p means; summary statistics only, so
        their pull towards the class's typical values cannot copy or average the images themselves).
        With ``fixed_pattern`` w > 0, G += w·:func:`fixed_pattern_loss` (G(x), y): the outputs' fine detail may be
        no more concentrated at fixed pixel positions over the batch than the real images' is, so that detail (the
        grain ``statistics`` asks for) cannot come as a fixed lattice of dots.
        With ``fixed_sign`` w > 0, G += w·:func:`fixed_sign_loss` (G(x), y, m): m the running mean of the outputs' fine
        detail (:meth:`update_detail_mean`, over about 100 batches), so that a pattern every output draws with the same
        sign, spread over the whole image (which ``fixed_pattern``, charging places, leaves free), costs its share.
        With ``shared_detail`` w > 0, G += w·:func:`shared_detail_loss` (G(x), y): two outputs' fine detail may be no more
        alike (mean squared cosine over the batch's pairs) than two real images' is, so a pattern the outputs share, with
        either sign and wherever it lies, costs as it appears, measured on the batch itself (no reference that can lag).
        With ``texture`` w > 0, G += w·:func:`vtgen.core.texture.texture_loss` (G(x), y): the feature covariances (centred
        Gram matrices) of a fixed random filter bank (texture statistics, Gatys et al. 2015; random filters,
        Ustyuzhaninov et al. 2017) of each output against those of the real image of its class in its row:
        orientation, scale and contrast of the class's texture, nothing of its layout.
        With ``contextual`` w > 0, G += w·:func:`vtgen.core.texture.contextual_loss` (G(x), y) on the same bank: every
        local feature of the real image of its class must be present somewhere in the output (Mechrez et al. 2018).
        With ``class_guidance`` w > 0, D's class head h also learns the class of the real images,
        D += w·CE(h(A(y)), c), and G is asked to be recognised as its input's class, G += w·CE(h(A(G(x))), c)
        (AC-GAN, Odena et al. 2017, with the classifier trained on real images only): a generator that is
        not told the class must read it from its input.
        With ``latent`` k > 0 the generator draws its own code z ~ N(0, I_k) per row, so the two rows of a
        pair differ in input and code, and the mode-seeking term keeps the code from being ignored.
        With ``semantic`` w > 0, G += w·:func:`recognition_loss` (guide, A(G(x)), c): a frozen real-only classifier
        of the target modality must recognise each augmented output as its input's class (the guide is trained apart
        from any classifier that scores the outputs). Measured: it buys recognition with pixel-scale stripes that
        fool classifiers of its kind (benchmarks/README.md, sixth round), so it is off by default.
        With ``mismatch`` w > 0, D also learns to reject real images under a wrong class, D += (w/2)·L(D(A(y), c'), fake),
        c' drawn uniformly from the other classes (:func:`other_classes`; the matching-aware discriminator of GAN-CLS,
        Reed et al. 2016), so that looking real is not enough: an output must look like its class.
        With ``nce`` w > 0, G += w·:func:`vtgen.core.patchnce.patch_nce_loss` between the generator's encoder features
        of G(x) and of x (levels :data:`NCE_LEVELS`; PatchNCE, Park et al. 2020): each output patch keeps the structure
        of the input patch at its place, with no pixel loss to a partner.
        With ``pack`` 2 D judges rows 2k and 2k+1 together (:meth:`packed`: PacGAN, Lin et al. 2018), real pairs against
        output pairs of the same class, in every term above that reads D.
        ``upsample`` 'resize' builds G's decoder from resize convolutions (no checkerboard without a pixel loss to hide it),
        'bilinear' from bilinear ones (resize, then a [1, 2, 1] blur: no 2 x 2 blocks lined up along rows and columns),
        'subpixel' from sub-pixel convolutions that start as resize ones (ICNR) and may learn finer detail,
        'balanced' from transposed ones whose sub-pixel kernels sum alike (no checkerboard of a constant input);
        ``padding`` 'reflect' pads G's encoder by reflection (no zero frame to draw border bands from).
        ``d_antialias`` starts D with a full-side stride-1 conv and blurs before each of its stride-2 convs
        (:class:`vtgen.core.models.BinomialBlur`), so D's gradient, what G learns from, carries no lattice of the
        strided convs while D still sees the finest patterns.
        ``generator`` 'resnet' trains :class:`vtgen.core.models.ResnetGenerator` in place of the U-Net.
        ``loss_g_l1`` is |G(x) − y| against the random partner: logged, never trained on.
        """
        policy = augment_policy(self.settings.get("diffaugment", True))
        augment = lambda images: diff_augment(images, policy)  # noqa: E731 (an empty policy is the identity)
        labels = labels.to(self.device)
        with self._autocast():
            fake = self.generator(x)
        loss_d = self._class_discriminator_step(y, fake, labels, augment)
        self.discriminator.requires_grad_(False)
        try:
            with self._autocast():
                d_fake, class_fake = self.discriminator.judge(*self.packed(augment(fake), labels))
            loss_g_gan = self._loss(d_fake, True)
            loss_g = self._class_generator_loss(loss_g_gan, x, y, fake, labels, class_fake, augment)
            self.opt_g.zero_grad(set_to_none=True)
            loss_g.backward()
            self.opt_g.step()
        finally:
            self.discriminator.requires_grad_(True)
        if self.average is not None:
            self.update_average()
        loss_g_l1 = F.l1_loss(fake.detach().float(), y)
        return dict(zip(LOSS_NAMES, (loss_d.detach(), loss_g_gan.detach(), loss_g_l1)))

    def packed(self, images: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What the class-pair discriminator judges: with ``pack`` 2, rows 2k and 2k+1 (two images of one class)
        side by side along the channels as one sample of their class (PacGAN, Lin et al. 2018: a pair of outputs
        that are too alike, or too unlike, is told from a pair of real images); with 1, ``images`` and ``labels``."""
        if self.pack == 1:
            return images, labels
        n, channels, height, width = images.shape
        return images.reshape(n // 2, 2 * channels, height, width), labels[0::2]

    def _class_discriminator_step(self, y, fake, labels, augment) -> torch.Tensor:
        """:meth:`class_step`'s discriminator update (adversarial, R1, mismatch and class-head terms); returns its loss."""
        cfg = self.settings
        r1, guidance, mismatch = cfg.get("r1", 0.0), cfg.get("class_guidance", 0.0), cfg.get("mismatch", 0.0)
        real = y.detach().requires_grad_(bool(r1))
        with self._autocast():
            real_packs, pack_labels = self.packed(augment(real), labels)
            real_features = self.discriminator.features(real_packs)
            d_real = self.discriminator.patch_logits(real_features, pack_labels)
            class_real = self.discriminator.class_logits(real_features)
            d_fake = self.discriminator(*self.packed(augment(fake.detach()), labels))
            if mismatch:
                wrong = other_classes(pack_labels, self.discriminator.num_classes)
                d_wrong = self.discriminator.patch_logits(real_features, wrong)
        loss_d = 0.5 * (self._loss(d_real, True) + self._loss(d_fake, False))
        if mismatch:
            loss_d = loss_d + 0.5 * mismatch * self._loss(d_wrong, False)
        if r1:
            loss_d = loss_d + r1 * r1_penalty(d_real, real)
        if guidance:
            loss_d = loss_d + guidance * F.cross_entropy(class_real.float(), pack_labels)
        self.opt_d.zero_grad(set_to_none=True)
        loss_d.backward()
        self.opt_d.step()
        return loss_d

    def _class_generator_loss(self, loss_g_gan, x, y, fake, labels, class_fake, augment) -> torch.Tensor:
        """:meth:`class_step`'s generator objective: ``loss_g_gan`` plus each weighted term, added in a fixed order."""
        cfg = self.settings
        seeking, guidance = cfg.get("mode_seeking", 0.0), cfg.get("class_guidance", 0.0)
        loss_g = loss_g_gan + seeking * mode_seeking_loss(fake.float(), y, cfg.get("mode_seeking_pool", 1),
                                                     cfg.get("mode_seeking_per_pair", False)) \
            if seeking else loss_g_gan
        if guidance:
            loss_g = loss_g + guidance * F.cross_entropy(class_fake.float(), self.packed(fake, labels)[1])
        statistics, texture, contextual = (cfg.get(k, 0.0) for k in ("statistics", "texture", "contextual"))
        if statistics:
            loss_g = loss_g + statistics * statistics_loss(fake.float(), y, cfg.get("statistics_spectrum", True),
                                                          cfg.get("statistics_pool", 1))
        fixed_pattern = cfg.get("fixed_pattern", 0.0)
        if fixed_pattern:
            loss_g = loss_g + fixed_pattern * fixed_pattern_loss(fake.float(), y)
        fixed_sign = cfg.get("fixed_sign", 0.0)
        if fixed_sign:
            self.update_detail_mean(fake)
            loss_g = loss_g + fixed_sign * fixed_sign_loss(fake.float(), y, self.detail_mean)
        shared_detail = cfg.get("shared_detail", 0.0)
        if shared_detail:
            loss_g = loss_g + shared_detail * shared_detail_loss(fake.float(), y)
        if texture:
            loss_g = loss_g + texture * texture_loss(fake, y, self.texture_bank)
        if contextual:
            loss_g = loss_g + contextual * contextual_loss(fake, y, self.texture_bank)
        nearest = cfg.get("nearest", 0.0)
        if nearest:
            draws = int(cfg.get("nearest_draws", 2))
            outputs = fake
            if draws > 1:  # the extra draws in one generator pass over the repeated batch (one launch per layer on a GPU)
                with self._autocast():
                    outputs = torch.cat([fake, self.generator(x.repeat(draws - 1, 1, 1, 1))])
            loss_g = loss_g + nearest * nearest_real_loss(outputs.float(), y, labels.repeat(draws), labels,
                                                          cfg.get("nearest_pool", 4))
        nce = cfg.get("nce", 0.0)
        if nce:
            with self._autocast():
                keys = self.generator.encode(x, self.nce_levels)
                queries = self.generator.encode(torch.cat([fake, x[:, 3:]], dim=1), self.nce_levels)
            loss_g = loss_g + nce * patch_nce_loss(queries, keys, self.nce_projection)
        semantic = cfg.get("semantic", 0.0)
        if semantic:
            with self._autocast():
                loss_g = loss_g + semantic * recognition_loss(self.guide, augment(fake), labels)
        return loss_g

    @property
    def output_generator(self) -> nn.Module:
        """The generator a run yields and is validated on: the weight average with ``ema`` > 0, else G itself."""
        return self.average if self.average is not None else self.generator

    @torch.no_grad()
    def update_average(self) -> None:
        """One step of the weight average after G's update t (counted from 1):
        θ̄ ← d_t·θ̄ + (1 − d_t)·θ_G with d_t = min(ema, (1 + t)/(10 + t)) (Polyak averaging of GAN weights,
        Yazıcı et al. 2019; the warm-up of TensorFlow's ExponentialMovingAverage, so that the average soon
        forgets the random start). Every floating tensor of G's state is averaged, BatchNorm's running
        statistics included; integer counters are copied."""
        self.average_updates += 1
        t = self.average_updates
        decay = min(self.ema_decay, (1 + t) / (10 + t))
        for average, live in zip(self.average.state_dict().values(), self.generator.state_dict().values()):
            if average.is_floating_point():
                average.lerp_(live, 1.0 - decay)
            else:
                average.copy_(live)

    @torch.no_grad()
    def update_detail_mean(self, outputs: torch.Tensor) -> None:
        """m ← d_t·m + (1 − d_t)·mean_b h(o_b), h = :func:`fine_detail`, d_t = min(:data:`FIXED_SIGN_DECAY`, (1 + t)/(10 + t))
        at update t (counted from 1; the warm-up of :meth:`update_average`): the fine detail the outputs share, sign included."""
        self.detail_updates += 1
        t = self.detail_updates
        batch_mean = fine_detail(outputs.detach().float()).mean(dim=0)
        if self.detail_mean is None:
            self.detail_mean = batch_mean
            return
        self.detail_mean.lerp_(batch_mean, 1.0 - min(FIXED_SIGN_DECAY, (1 + t) / (10 + t)))

    def generator_norm(self) -> float:
        """L2 norm of all generator parameters, ‖θ_G‖₂ = sqrt(Σ θ²) (a host sync)."""
        return float(torch.linalg.vector_norm(torch.stack(
            [torch.linalg.vector_norm(p.detach().float()) for p in self.generator.parameters()])))

    def state_dict(self) -> dict:
        """Both networks and both optimisers, under the keys of :data:`STATE_KEYS`, PatchNCE's projection heads
        under 'nce_projection' when ``nce`` is on, the weight average under 'average' when ``ema`` is on, and the running
        mean of the outputs' fine detail under 'detail_mean' once ``fixed_sign`` has updated it."""
        state = {"generator": self.generator.state_dict(), "discriminator": self.discriminator.state_dict(),
                 "opt_g": self.opt_g.state_dict(), "opt_d": self.opt_d.state_dict()}
        if self.nce_projection is not None:
            state["nce_projection"] = self.nce_projection.state_dict()
        if self.average is not None:
            state["average"] = {"generator": self.average.state_dict(), "updates": self.average_updates}
        if self.detail_mean is not None:
            state["detail_mean"] = {"mean": self.detail_mean.clone(), "updates": self.detail_updates}
        return state

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` returned (copies: torch's optimiser ``load_state_dict`` would share
        the state tensors with their source). Raises KeyError for a missing part and RuntimeError or
        ValueError when a part does not fit these networks (other sizes or widths)."""
        self.generator.load_state_dict(state["generator"])
        self.discriminator.load_state_dict(state["discriminator"])
        self.opt_g.load_state_dict(copy.deepcopy(state["opt_g"]))
        self.opt_d.load_state_dict(copy.deepcopy(state["opt_d"]))
        if self.nce_projection is not None:
            self.nce_projection.load_state_dict(state["nce_projection"])
        if self.average is not None:
            self.average.load_state_dict(state["average"]["generator"])
            self.average_updates = int(state["average"]["updates"])
        if "detail_mean" in state:
            self.detail_mean = state["detail_mean"]["mean"].clone().to(self.device)
            self.detail_updates = int(state["detail_mean"]["updates"])


def other_classes(labels: torch.Tensor, num_classes: int) -> torch.Tensor:
    """For each class index c in ``labels``, one of the other ``num_classes`` − 1 classes, uniformly:
    (c + k) mod K with k ~ U{1, …, K − 1} drawn from torch's global generator."""
    if num_classes < 2:
        raise ValueError(f"a wrong class needs at least 2 classes, got {num_classes}")
    shift = torch.randint(1, num_classes, labels.shape).to(labels.device)
    return (labels + shift) % num_classes


def r1_penalty(real_logits: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """(1/2)·E‖∇ₓ D̄(x)‖² over the real images ``real`` (which require grad), D̄ the mean of each image's logits, as
    the adversarial loss averages them (Mescheder et al. 2018, eq. 9, without γ); differentiable (create_graph)
    so D can be trained on it. The mean keeps a weight's meaning at any image size: on the sum of a 7 x 7
    PatchGAN's logits the same weight would act 49² = 2,401 times as strongly."""
    per_image = real_logits.float().reshape(real_logits.shape[0], -1).mean(dim=1)
    (gradient,) = torch.autograd.grad(per_image.sum(), real, create_graph=True)
    return 0.5 * gradient.pow(2).sum(dim=tuple(range(1, gradient.dim()))).mean()


def nearest_real_loss(outputs: torch.Tensor, targets: torch.Tensor, output_labels: torch.Tensor,
                      target_labels: torch.Tensor, pool: int = 4) -> torch.Tensor:
    """Mean over the real ``targets`` of the L1 distance, between ``pool`` x ``pool`` means, to the nearest of the
    ``outputs`` of the target's class: implicit maximum likelihood estimation (Li & Malik 2018; conditional, Li et al.
    2020), which pulls only the output nearest each real image towards it, so every real image of a class gets an
    output near it (coverage) and no output is pulled to the class mean. A target with no output of its class adds 0."""
    o = F.avg_pool2d(outputs, pool) if pool > 1 else outputs
    t = F.avg_pool2d(targets.detach().float(), pool) if pool > 1 else targets.detach().float()
    distance = (t[:, None] - o[None]).abs().mean(dim=(2, 3, 4))
    same = target_labels.to(distance.device)[:, None] == output_labels.to(distance.device)[None, :]
    nearest = distance.masked_fill(~same, float("inf")).min(dim=1).values
    return torch.where(torch.isfinite(nearest), nearest, torch.zeros_like(nearest)).mean()


def statistics_loss(outputs: torch.Tensor, targets: torch.Tensor, spectrum: bool = True, pool: int = 1) -> torch.Tensor:
    """Mean over images of |μ(o) − μ(t)|₁/3 + |σ(o) − σ(t)|₁/3 + |s(o) − s(t)|₁/K: per-channel mean μ and standard
    deviation σ over the pixels, and s the log10 radial power profile of the grey (K bins; the score stage's
    spectrum metric, :func:`vtgen.core.spectrum.rgb_log_radial_profiles`); with ``spectrum`` false the first two
    terms only (colour and contrast, nothing that asks for fine grain). With ``pool`` p > 1, σ is taken over the
    p x p means (``avg_pool2d``) of both images: contrast at the scale of shapes, which a lattice of dots finer
    than p px cannot supply. ``targets`` is data (detached)."""
    targets = targets.detach().float()
    mean = (outputs.mean(dim=(2, 3)) - targets.mean(dim=(2, 3))).abs().mean()
    coarse_outputs, coarse_targets = (F.avg_pool2d(outputs, pool), F.avg_pool2d(targets, pool)) if pool > 1 else (outputs, targets)
    spread = (coarse_outputs.std(dim=(2, 3)) - coarse_targets.std(dim=(2, 3))).abs().mean()
    if not spectrum:
        return mean + spread
    power = (rgb_log_radial_profiles(outputs) - rgb_log_radial_profiles(targets)).abs().mean()
    return mean + spread + power


def fine_detail(images: torch.Tensor) -> torch.Tensor:
    """Each pixel minus the mean of its 3 x 3 neighbourhood (edges replicated): the high-pass part of ``images``."""
    return images - F.avg_pool2d(F.pad(images, (1, 1, 1, 1), mode="replicate"), 3, stride=1)


def detail_concentration(images: torch.Tensor) -> torch.Tensor:
    """c = var_p e(p) / (mean_p e(p)² + ε), e(p) = mean over the images and channels of h(p)², h = :func:`fine_detail`:
    the squared coefficient of variation over pixel positions of where ``images`` (N x C x H x W) keep their fine
    detail. Detail spread evenly or at places that differ from image to image gives a low c; detail at the same
    places in every image, whatever its sign, a high one. Unchanged when all detail is scaled."""
    energy = fine_detail(images).pow(2).mean(dim=(0, 1))
    return energy.var(correction=0) / (energy.mean().pow(2) + FIXED_PATTERN_EPS)


def fixed_pattern_loss(outputs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """max(0, c(outputs) − c(targets)) with c = :func:`detail_concentration`: fine detail at fixed places (the dot
    lattices of transposed convolutions, Odena et al. 2016) costs what it adds beyond the real batch's own,
    while the amount of detail is free. Squared detail, so dots that flip sign from output to output cost as
    much as dots that do not (a signed batch mean, tried first, was evaded that way: benchmarks/README.md,
    Fifty-fourth round). ``targets`` is data (detached)."""
    return torch.relu(detail_concentration(outputs) - detail_concentration(targets.detach().float()))


def fixed_sign_share(images: torch.Tensor, pattern: torch.Tensor) -> torch.Tensor:
    """s = mean_b ⟨h_b, u⟩² / (mean_b ‖h_b‖² + ε), u = m/‖m‖, h = :func:`fine_detail` of ``images`` (N x C x H x W), m =
    ``pattern`` (C x H x W): the share of the images' fine-detail energy that lies along one fixed signed pattern.
    Squared per image, so an image that draws the pattern with the opposite sign pays as much; unchanged when all
    detail is scaled; 0 for a zero pattern."""
    detail = fine_detail(images)
    norm = pattern.norm()
    if float(norm) == 0.0:
        return detail.sum() * 0.0
    along = (detail * (pattern / norm)).flatten(1).sum(dim=1)
    return along.pow(2).mean() / (detail.pow(2).flatten(1).sum(dim=1).mean() + FIXED_PATTERN_EPS)


def fixed_sign_loss(outputs: torch.Tensor, targets: torch.Tensor, pattern: torch.Tensor) -> torch.Tensor:
    """max(0, s(outputs) − s(targets)) with s = :func:`fixed_sign_share` along ``pattern``, the running mean of the outputs'
    fine detail (detached): a pattern the outputs share with one sign (a lattice over the whole image, whose detail is
    not concentrated at a few places, so :func:`fixed_pattern_loss` leaves it free) costs its share of each output's
    detail beyond what real images of the batch keep along it. ``targets`` is data (detached)."""
    pattern = pattern.detach().float()
    return torch.relu(fixed_sign_share(outputs, pattern) - fixed_sign_share(targets.detach().float(), pattern))


def detail_overlap(images: torch.Tensor) -> torch.Tensor:
    """o = Σ_{i≠j} ⟨h_i, h_j⟩² / (Σ_{i≠j} ‖h_i‖²‖h_j‖² + ε), h = :func:`fine_detail` of each of the N images (N x C x H x W,
    N ≥ 2), flattened: how alike two images' fine detail is, the mean squared cosine between two of them weighted by
    their energies (a sum over pairs in the denominator, so a nearly flat image cannot make it unstable). In [0, 1]
    (Cauchy-Schwarz): 1 when all share one pattern, whatever each one's sign and amount of it; about 1/D for
    independent detail of D values; a pattern making up a share f of each image's detail gives about f²."""
    n = images.shape[0]
    if n < 2:
        raise ValueError(f"detail overlap compares images in pairs: it needs at least 2 images, got {n}")
    detail = fine_detail(images).flatten(1)
    gram = detail @ detail.T
    energy = gram.diagonal()
    alike = gram.pow(2).sum() - energy.pow(2).sum()
    scale = energy.sum().pow(2) - energy.pow(2).sum()
    return alike / (scale + FIXED_PATTERN_EPS)


def shared_detail_loss(outputs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """max(0, o(outputs) − o(targets)) with o = :func:`detail_overlap`: fine detail the outputs of a batch have in common
    (a lattice of a transposed convolution, a fixed motif) costs what it adds beyond the real batch's own (a sensor's
    fixed pattern is allowed), computed on the batch itself, so unlike :func:`fixed_sign_loss`'s running mean it has no
    reference the generator can move away from; squared, so a pattern drawn with flipped signs costs the same.
    ``targets`` is data (detached)."""
    return torch.relu(detail_overlap(outputs) - detail_overlap(targets.detach().float()))


def mode_seeking_loss(outputs: torch.Tensor, targets: torch.Tensor, pool: int = 1, per_pair: bool = False) -> torch.Tensor:
    """max(0, 1 − r), r = mean|o₂ₖ − o₂ₖ₊₁| / mean|t₂ₖ − t₂ₖ₊₁| over the row pairs (2k, 2k+1) of the batch,
    where the two rows of a pair are of one class and ``targets`` are real images of those classes.

    Zero once two outputs of a class differ as much as two real images of it do: the mode-seeking ratio of
    Mao et al. 2019 (eq. 3), clipped as in Yang et al. 2019 (DSGAN), with the real spread of the class as
    its scale so that a low-contrast target modality (touch) is not pushed to more contrast than it has
    (an unclipped 1/r, tried first, tripled the output contrast of V2T). With ``pool`` p > 1 both gaps are
    taken between p x p means (``avg_pool2d``), so that varied layout counts and pixel noise, which two
    outputs can differ by at no cost in realism, does not. With ``per_pair`` the hinge is taken per pair k,
    mean_k max(0, 1 − |o₂ₖ − o₂ₖ₊₁| / |t₂ₖ − t₂ₖ₊₁|) (each gap a mean over pixels), so that one pair's large gap (an
    outlier such as a dark vignette or a saturated corner) no longer pays for another pair's collapse.
    ``targets`` is detached (data); N must be even and at least 2."""
    n = outputs.shape[0]
    if n < 2 or n % 2:
        raise ValueError(f"mode seeking pairs rows (2k, 2k+1): the batch needs an even size >= 2, got {n}")
    if pool > 1:
        outputs, targets = F.avg_pool2d(outputs, pool), F.avg_pool2d(targets.detach().float(), pool)
    if per_pair:
        out_gap = (outputs[0::2] - outputs[1::2]).abs().flatten(1).mean(1)
        real_gap = (targets[0::2] - targets[1::2]).abs().flatten(1).mean(1).detach().float()
        return torch.relu(1.0 - out_gap / real_gap.clamp_min(MODE_SEEKING_EPS)).mean()
    out_gap = (outputs[0::2] - outputs[1::2]).abs().mean()
    real_gap = (targets[0::2] - targets[1::2]).abs().mean().detach().float()
    return torch.relu(1.0 - out_gap / real_gap.clamp_min(MODE_SEEKING_EPS))


def training_step_flops(settings: dict, input_channels: int = 3, precision: str = "fp32",
                        guide: nn.Module | None = None) -> int:
    """Floating-point operations of one :meth:`TranslatorTraining.step` (forward and backward of both networks,
    and of ``guide`` when ``semantic`` needs it) at ``settings``' size, widths and batch, counted by
    ``torch.utils.flop_counter.FlopCounterMode`` on the CPU (matmuls and convolutions, 2 per multiply-add). Runs
    one step on random data; the global RNG is restored."""
    from torch.utils.flop_counter import FlopCounterMode

    rng = torch.get_rng_state()
    try:
        classes = guide.num_classes if guide is not None else 2
        training = TranslatorTraining(settings, "cpu", precision, input_channels, classes,
                                      None if guide is None else copy.deepcopy(guide))
        size, batch = settings["size"], settings["batch_size"]
        x, y = torch.rand(batch, input_channels, size, size) * 2 - 1, torch.rand(batch, 3, size, size) * 2 - 1
        with FlopCounterMode(display=False) as counter:
            training.step(x, y, torch.arange(batch) % 2)
        return int(counter.get_total_flops())
    finally:
        torch.set_rng_state(rng)
