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
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    torch.save({"kind": type(model).__name__, "config": asdict(model.config), "state_dict": state, **extra}, partial)
    partial.replace(path)


def load_model_file(path: str | Path, model_class: type, config_class: type, map_location="cpu"):
    """A model_class in eval mode from a file of save_model_file or a training checkpoint, its
    .fps the frame rate it was trained at (30 when the file does not say). ValueError naming the
    file when it is no weights file or holds another kind of network."""
    not_ours = f"{path} is not a {model_class.__name__} weights file"
    try:
        data = torch.load(path, map_location=map_location, weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError) as error:
        raise ValueError(f"{not_ours} ({type(error).__name__})") from None
    if not isinstance(data, dict):
        raise ValueError(not_ours)
    if "model" in data:  # a training checkpoint: the frame rate is in its run config
        fps, data = data["config"].get("fps", 30.0), data["model"]
    else:
        fps = data.get("fps", 30.0)
    if data.get("kind", model_class.__name__) != model_class.__name__:
        raise ValueError(f"{path} holds {data['kind']} weights, not {model_class.__name__} weights")
    names = {f.name for f in fields(config_class)}
    try:
        model = model_class(config_class(**{k: v for k, v in data["config"].items() if k in names}))
        model.load_state_dict(data["state_dict"])
    except (KeyError, TypeError, RuntimeError) as error:  # another network's config or tensors
        raise ValueError(f"{not_ours}: {str(error).splitlines()[0]}") from None
    model.fps = float(fps)
    return model.eval()
