"""Training the learned retargeter, unpaired, across two skeleton domains: ``humotion train retarget --help``.

    from humotion.retarget.train import RetargetTrainConfig, train
    summary = train(RetargetTrainConfig(out_dir="runs/retarget", steps=3000, threads=1))

Data: per domain the clips of its source folders under ../shared/data/mocap whose skeletons are
of that domain (humotion.retarget.domains): A, the CMU ASF skeletons (31 joints, each subject
its own bone lengths), and B, the 100-joint game rig (cmu_iclone_ccskeleton). Subjects in
`held_out` (default the CMU subjects 01, 02, 03, 05, 06, whose takes exist on both skeletons and
are bench/retarget_eval.py's ground truth) are left out of both, and A also leaves out B's
subjects (CMU 07), so no take is on both sides: the domains share no motion (unpaired). hdm05_jointlearning
is evaluation-only. Windows of `length` frames at `fps`, each clip also mirrored.

Every step takes a batch of A windows a and of B windows b and retargets (E: motion encoder,
D: decoder, s: skeleton codes of a body; a' is another A body, the batch's bodies rolled by one):
    reconstruction  D_A(E_A(a), s_a) = a,  D_B(E_B(b), s_b) = b
    retargeting     ab = D_B(E_A(a), s_b),  ba = D_A(E_B(b), s_a),  aa' = D_A(E_A(a), s_a')
    cycle           D_A(E_B(ab), s_a) = a,  D_B(E_A(ba), s_b) = b,  D_A(E_A(aa'), s_a) = a
Losses (weights in config.weights): rec and cycle, squared error of the normalised features;
position, of the pelvis-relative joint positions in units of body height (forward kinematics),
on reconstructions and cycles; effector, on every retargeted motion, of the positions of the
END_EFFECTORS (head, wrists, ankles, toes) relative to the pelvis in units of each body's height
against its source's, and root, of its root features (velocity and height in hip heights)
against its source's: the usual terms that tie the domains' latent spaces together (without
them cycles can be met by any mapping); adversarial, least squares, the domain's discriminator scoring ab, ba and aa' as real,
while the discriminators learn real = 1 and retargeted = 0 (term discriminator). Generator and
discriminators take one Adam step together: each term's gradient reaches only its own side
(discriminator weights are frozen in the generator's term, retargeted motions detached in the
discriminator's).

Output folder and resume: as every training command (humotion.training): checkpoints,
log.jsonl and retarget_net.pt (final weights, config, statistics, for
humotion.retarget.learned.retarget_learned). No validation: every take of a subject on both
skeletons is kept for the benchmark.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import torch
from torch.nn.functional import mse_loss

from humotion.data import MotionCollection
from humotion.retarget.data import DomainWindows
from humotion.retarget.domains import DomainSpec, joint_positions, mean_rotations
from humotion.retarget.networks import RetargetConfig, RetargetNet, save_retarget_net
from humotion.training import RunConfig, Session, fit

log = logging.getLogger("humotion.retarget")

DOMAINS = {"cmu_asf": ("cmu_sxaxmz", "cmu_cyun9601", "cmu_mocgui_s02", "cmu_visdoom_mocapplayer", "cmu_fairmotion"),
           "iclone_cc": ("cmu_iclone_ccskeleton",)}
HELD_OUT = ("cmu-01", "cmu-02", "cmu-03", "cmu-05", "cmu-06")
WEIGHTS = {"rec": 1.0, "cycle": 1.0, "position": 50.0, "effector": 100.0, "root": 1.0, "adversarial": 0.05}


@dataclass
class RetargetTrainConfig(RunConfig):
    """Everything a retargeter training run needs; saved in every checkpoint. The run settings
    (data, steps, seed, device, files) are humotion.training.RunConfig's; here also:

    domains: domain name -> source folders, A first then B. held_out: subjects left out of both.
    length, stride: window frames and frames between windows. mirror: add mirrored clips.
    weights: loss term -> weight (module docstring). model: network sizes (domains filled in).
    """

    out_dir: str = "runs/retarget"
    train_split: str | None = None
    val_split: str | None = None
    batch_size: int = 8
    lr: float = 1e-3
    grad_clip: float = 10.0
    checkpoint_every: int = 200
    length: int = 64
    """Window length, frames."""
    stride: int = 4
    """Frames between training windows."""
    mirror: bool = True
    domains: dict = field(default_factory=lambda: dict(DOMAINS))
    held_out: tuple[str, ...] = HELD_OUT
    """Subjects left out of both domains (repeatable)."""
    weights: dict = field(default_factory=lambda: dict(WEIGHTS))
    model: RetargetConfig = field(default_factory=RetargetConfig)

    def __post_init__(self):
        if isinstance(self.model, dict):
            self.model = RetargetConfig(**self.model)
        self.domains = {name: tuple(sources) for name, sources in self.domains.items()}
        if len(self.domains) != 2:
            raise ValueError(f"training takes two skeleton domains, got {list(self.domains)}")


def load_domains(config: RetargetTrainConfig, progress: bool = False):
    """Per domain (config order): its DomainSpec, DomainWindows and the mean rotations of its
    unmodelled joints (len(spec.others), 4). A domain leaves out the held-out subjects and those
    of the domains after it (B keeps its subjects, A drops them). The reference skeleton of a
    domain is the most common joint structure among its clips; clips of another structure are
    kept when they are of the domain (domains.DomainSpec.indices), left out otherwise."""
    collection = MotionCollection.load(config.data_root, progress=progress)
    collection = collection.filter(sources=config.sources, exclude=config.exclude)
    candidates = {name: [c for c in collection.filter(sources=sources).clips if c.subject not in config.held_out]
                  for name, sources in config.domains.items()}
    out = []
    for i, (name, sources) in enumerate(config.domains.items()):
        later = {c.subject for other in list(candidates.values())[i + 1:] for c in other}
        clips = [c for c in candidates[name] if c.subject not in later]      # no subject in two domains
        clips = clips[:config.max_clips] if config.max_clips else clips
        if not clips:
            raise ValueError(f"domain {name}: no clips in {', '.join(sources)} under {config.data_root} outside the "
                             f"held-out subjects {', '.join(config.held_out)} and those of later domains")
        common = max({c.signature for c in clips}, key=lambda s: sum(c.signature == s for c in clips))
        spec = DomainSpec.of(name, next(c for c in clips if c.signature == common).load().skeleton)
        motions = [m for m in (c.load() for c in clips) if spec.indices(m.skeleton) is not None]
        windows = DomainWindows.from_motions(spec, motions, config.length, config.stride, config.fps, config.mirror)
        log.info("domain %s: %d clips (%s), %d windows on %d bodies", name, len(motions),
                 ", ".join(sorted({c.subject for c in clips})), len(windows), len(windows.bodies))
        out.append((spec, windows, mean_rotations(motions, spec.others)))
    return out


def _frozen(module: torch.nn.Module, *inputs) -> torch.Tensor:
    """module(*inputs) with its parameters detached: gradients reach the inputs only."""
    return torch.func.functional_call(module, {k: v.detach() for k, v in module.named_parameters()}, inputs)


class Objective(RetargetNet):
    """A RetargetNet whose forward is the training objective on one batch of each domain (one
    forward per step, as DistributedDataParallel wants); same config and state dict as the net."""

    def __init__(self, config: RetargetConfig, weights: dict[str, float]):
        super().__init__(config)
        self.weights = weights

    def _raw(self, domain: str, features):
        return self.normalizers[domain].denormalize(*features)

    def _positions(self, domain: str, rotations: torch.Tensor, body: dict) -> torch.Tensor:
        """(B, T, J, 3) pelvis-relative joint positions in units of body height."""
        return joint_positions(self.domains[domain], rotations, body["offsets"]) / body["height"][:, None, None, None]

    def forward(self, a: dict, b: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """a, b: batches of domains A and B (data.DomainWindows.batch: rotations (B, T, J, 6),
        root (B, T, 3), offsets (B, J, 3), height (B,) metres). Returns (total, terms): the
        weighted loss and each term by name, scalar tensors."""
        A, B = (d.name for d in self.config.domains)
        a2 = {k: a[k].roll(1, 0) for k in ("offsets", "height")}                   # other A bodies
        batch = {A: a, B: b}
        x = {d: self.normalizers[d].normalize(batch[d]["rotations"], batch[d]["root"]) for d in (A, B)}
        code = {d: self.skeleton_encoders[d](batch[d]["offsets"]) for d in (A, B)}
        latent = {d: self.encoders[d](*x[d], code[d]) for d in (A, B)}
        truth = {d: self._positions(d, batch[d]["rotations"], batch[d]) for d in (A, B)}
        terms = dict.fromkeys(("rec", "cycle", "position", "effector", "root", "adversarial", "discriminator"), 0.0)

        def compare(domain: str, features) -> tuple[torch.Tensor, torch.Tensor]:
            """(feature error, position error) of features against the domain's batch."""
            positions = self._positions(domain, self._raw(domain, features)[0], batch[domain])
            return sum(mse_loss(p, t) for p, t in zip(features, x[domain])), mse_loss(positions, truth[domain])

        for d in (A, B):
            rec_error, position_error = compare(d, self.decoders[d](latent[d], code[d]))
            terms["rec"], terms["position"] = terms["rec"] + rec_error, terms["position"] + position_error
            real = self.discriminators[d](*x[d])
            terms["discriminator"] = terms["discriminator"] + mse_loss(real, torch.ones_like(real))
        # (source, target, target bodies, their skeleton codes): A -> B, B -> A, A -> other A bodies
        for source, target, body, target_code in ((A, B, b, code[B]), (B, A, a, code[A]), (A, A, a2, code[A].roll(1, 0))):
            moved = self.decoders[target](latent[source], target_code)
            cycle = self.decoders[source](self.encoders[target](*moved, target_code), code[source])
            cycle_error, position_error = compare(source, cycle)
            terms["cycle"], terms["position"] = terms["cycle"] + cycle_error, terms["position"] + position_error
            rotations, root = self._raw(target, moved)
            effectors = self._positions(target, rotations, body)[..., self.domains[target].effectors, :]
            wanted = truth[source][..., self.domains[source].effectors, :]
            terms["effector"] = terms["effector"] + mse_loss(effectors, wanted)
            terms["root"] = terms["root"] + mse_loss(root, batch[source]["root"])
            fake = _frozen(self.discriminators[target], *moved)
            terms["adversarial"] = terms["adversarial"] + mse_loss(fake, torch.ones_like(fake))
            fake = self.discriminators[target](*(f.detach() for f in moved))
            terms["discriminator"] = terms["discriminator"] + mse_loss(fake, torch.zeros_like(fake))
        total = terms["discriminator"] + sum(w * terms[k] for k, w in self.weights.items())
        return total, terms


def train(config: RetargetTrainConfig) -> dict:
    """Train (or resume) the learned retargeter; returns a summary dict (step, losses, files)."""
    session = Session(config)
    start = time.perf_counter()
    domains = load_domains(config, progress=session.show)
    session.echo(f"data: {', '.join(f'{s.name} {len(w)} windows' for s, w, _ in domains)} "
                 f"({time.perf_counter() - start:.0f} s)")
    sizes = {**vars(config.model), "domains": [s for s, _, _ in domains], "window": config.length}
    model = Objective(RetargetConfig(**sizes), config.weights)
    for spec, windows, others in domains:
        features = [windows.batch(range(i, min(i + 256, len(windows)))) for i in range(0, len(windows), 256)]
        model.normalizers[spec.name].fit(torch.cat([f["rotations"] for f in features]),
                                         torch.cat([f["root"] for f in features]), others)
    model = model.to(session.device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    (_, windows_a, _), (_, windows_b, _) = domains
    steps_per_epoch = math.ceil(math.ceil(len(windows_a) / session.world) / config.batch_size)

    def batches(epoch: int, skip: int):
        order_a = session.epoch_indices(len(windows_a), epoch)
        repeats = math.ceil(len(order_a) / len(windows_b))
        # B's order per process (A's is split between processes by epoch_indices); rank 0 as one process
        shuffle = torch.Generator().manual_seed(config.seed * 1000 + epoch + 7919 * session.rank)
        order_b = torch.cat([torch.randperm(len(windows_b), generator=shuffle) for _ in range(repeats)]).tolist()
        for i in range(skip * config.batch_size, len(order_a), config.batch_size):
            items = order_a[i:i + config.batch_size]
            yield tuple({k: v.to(session.device) for k, v in w.batch(chosen).items()}
                        for w, chosen in ((windows_a, items), (windows_b, order_b[i:i + len(items)])))

    def export(module, path, **extra):
        net = RetargetNet(module.config)
        net.load_state_dict(module.state_dict())
        net.fps = config.fps
        save_retarget_net(net, path, **extra)

    return fit(session, model, optimizer, steps_per_epoch=steps_per_epoch, batches=batches,
               loss=lambda model, batch: model(*batch), validate=None, save_weights=export,
               weights_name="retarget_net")
