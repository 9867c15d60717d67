"""Weight files of humotion's networks: one format for all (weights, config, frame rate).

A file is a torch.save'd dict {"kind": class name, "config": the model's config dataclass as a
dict, "state_dict": tensors, "fps": frame rate, ...extra plain fields}; a training checkpoint
holds one under "model" (its frame rate in the run's "config"). Loading reads tensors and plain
values only (weights_only), never code.
"""

from __future__ import annotations

import pickle
from dataclasses import asdict, fields
from pathlib import Path

import torch

from humotion.atomic import atomic_file


def save_model_file(model: torch.nn.Module, path: str | Path, half_over: int | None = None, **extra) -> None:
    """Save model (its .config a dataclass; unwrapped from DistributedDataParallel) to path, with
    extra plain fields (fps, the training step, validation). half_over: store floating-point
    tensors of more numbers than this as float16 (about half the file; they load back into the
    model's float32 parameters), marked by a "half" field. Written to a temporary file first, so
    path never holds a half-written file."""
    model = getattr(model, "module", model)
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    if half_over is not None:
        state = {k: v.half() if v.is_floating_point() and v.numel() > half_over else v for k, v in state.items()}
        extra["half"] = True
    with atomic_file(path) as file:
        torch.save({"kind": type(model).__name__, "config": asdict(model.config), "state_dict": state, **extra}, file)


def load_model_file(path: str | Path, model_class: type, config_class: type, map_location="cpu",
                    inside: tuple[str, str] | None = None, optional: frozenset[str] = frozenset()):
    """A model_class in eval mode from a file of save_model_file or a training checkpoint, its
    .fps the frame rate it was trained at (30 when the file does not say).

    inside (config field, attribute): for a network trained as a part of a larger module, where a
    checkpoint of that module keeps the network's config and the network (the body model's
    BodyTrainer: ("model", "body"), its tensors "body.*"). optional: names of tensors a file may
    lack; the model keeps its own values of them.

    ValueError naming the file and the problem in one line: the file is damaged, truncated or of
    another format, holds another kind of network, or its config or tensors do not fit the model
    (missing or unexpected tensors named, or the first tensor of another size)."""
    not_ours = f"{path} is not a {model_class.__name__} weights file"
    fps, data = _network(_read(path, not_ours, map_location), inside, not_ours)
    if data.get("kind", model_class.__name__) != model_class.__name__:
        raise ValueError(f"{path} holds {data['kind']} weights, not {model_class.__name__} weights")
    names = {f.name for f in fields(config_class)}
    try:
        model = model_class(config_class(**{k: v for k, v in data["config"].items() if k in names}))
        missing, unexpected = model.load_state_dict(data["state_dict"], strict=False)
    except (KeyError, TypeError, RuntimeError) as error:  # another network's config or tensors
        raise ValueError(f"{not_ours}: {_first_line(error)}") from None
    problems = [f"{what} tensors {sorted(keys)}" for what, keys in (("missing", set(missing) - optional),
                                                                   ("unexpected", unexpected)) if keys]
    if problems:
        raise ValueError(f"{not_ours}: {', '.join(problems)}")
    model.fps = float(fps)
    return model.eval()


def _read(path: str | Path, not_ours: str, map_location) -> dict:
    """torch.load's dict of tensors and plain values; ValueError `not_ours` and why for a file it
    cannot read (damaged, truncated, empty, another format) or that holds no dict."""
    try:
        data = torch.load(path, map_location=map_location, weights_only=True)
    except EOFError:
        raise ValueError(f"{not_ours}: it is empty or ends early") from None
    except pickle.UnpicklingError:
        raise ValueError(f"{not_ours}: it is not a torch file of tensors and plain values") from None
    except RuntimeError as error:   # a damaged or truncated zip archive, among others
        raise ValueError(f"{not_ours}: {_first_line(error)}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{not_ours}: it holds a {type(data).__name__}, not a dict")
    return data


def _network(data: dict, inside: tuple[str, str] | None, not_ours: str) -> tuple[float, dict]:
    """(frame rate, the network's dict {"config": dict, "state_dict": dict, "kind"...}) of a file's
    dict: the dict itself, or a training checkpoint's "model" (its frame rate in the run's
    "config"), or the part `inside` of that (see :func:`load_model_file`); ValueError `not_ours`
    where it holds no config and tensors."""
    try:
        if "model" not in data:
            fps = data.get("fps", 30.0)
        else:
            fps, data = data["config"].get("fps", 30.0), data["model"]
            if inside is not None:
                field, prefix = inside[0], inside[1] + "."
                data = {"config": data["config"][field], "state_dict": {
                    k[len(prefix):]: v for k, v in data["state_dict"].items() if k.startswith(prefix)}}
        if isinstance(data["config"], dict) and isinstance(data["state_dict"], dict):
            return fps, data
    except (KeyError, TypeError, AttributeError):   # a checkpoint of another layout
        pass
    raise ValueError(f"{not_ours}: it holds no config and tensors")


def _first_line(error: Exception) -> str:
    """The first sentence of an error's message that says what is wrong (torch's state_dict
    errors open with a header line, its load errors go on with advice), or the error's type."""
    lines = [line.strip() for line in str(error).splitlines()]
    lines = [line for line in lines if line and not line.startswith("Error(s) in loading state_dict")]
    return lines[0].split(". ")[0] if lines else type(error).__name__
