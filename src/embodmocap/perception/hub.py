"""Where model weights come from: a local folder, or a Hugging Face hub id in the standard cache.

Every model backend (RT-DETR, ViTPose, SAM 2, Prompt Depth Anything) takes ``model``: either a
folder written by ``save_pretrained`` or a hub id such as ``PekingU/rtdetr_r50vd_coco_o365``; an
empty value means the role's default id (:data:`DEFAULT_MODELS`). A hub id is looked up in the
standard Hugging Face cache (``HF_HUB_CACHE``, else ``HF_HOME/hub``, else
``~/.cache/huggingface/hub``, the same folder ``hf download`` fills) and, when it is not there,
downloaded into it, unless downloads are off (``offline=True``, i.e. ``--offline``, or
``HF_HUB_OFFLINE=1`` / ``TRANSFORMERS_OFFLINE=1`` in the environment). Only the files the loaders read
are fetched (:data:`WEIGHT_PATTERNS`: configs and safetensors weights), never a repository's
original training checkpoints. When a model cannot be had, the error names the id, the cache folder
and the command that fetches it.

The environment is read when a model is resolved (not when the package is imported), so a variable
set by a test or a wrapper script counts. huggingface_hub is imported only here and only when a
hub id is resolved (extra ``perception``).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

from embodmocap.errors import InputError, require

log = logging.getLogger(__name__)

DEFAULT_MODELS: dict[str, str] = {
    "detector": "PekingU/rtdetr_r50vd_coco_o365",
    "keypoints": "usyd-community/vitpose-base-simple",
    "masks": "facebook/sam2.1-hiera-tiny",
    "depth": "depth-anything/prompt-depth-anything-vits-hf",
}
"""Role -> the hub id used when no model is given: RT-DETR (ResNet-50, COCO + Objects365), ViTPose
base (COCO-17), SAM 2.1 tiny (video) and Prompt Depth Anything ViT-S (the transformers port)."""

WEIGHT_PATTERNS: tuple[str, ...] = ("*.json", "*.safetensors")
"""Files of a hub repository that are downloaded (and must be in the cache offline): the model and
preprocessor configs and the safetensors weights. Online and offline look-ups use the same list, so
a snapshot this module downloaded counts as complete offline."""

_HUB_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+$")
_TRUE = {"1", "on", "yes", "true"}


def hub_cache_dir() -> Path:
    """The Hugging Face hub cache folder the environment selects now (as huggingface_hub resolves it):
    ``HF_HUB_CACHE``, else ``HUGGINGFACE_HUB_CACHE``, else ``HF_HOME/hub``, else
    ``$XDG_CACHE_HOME/huggingface/hub``, else ``~/.cache/huggingface/hub``."""
    env = os.environ
    home = env.get("HF_HOME") or os.path.join(env.get("XDG_CACHE_HOME") or os.path.join("~", ".cache"), "huggingface")
    cache = env.get("HF_HUB_CACHE") or env.get("HUGGINGFACE_HUB_CACHE") or os.path.join(home, "hub")
    return Path(os.path.expandvars(cache)).expanduser()


def downloads_off(offline: bool = False) -> bool:
    """True when models must come from disk only: ``offline``, or HF_HUB_OFFLINE / TRANSFORMERS_OFFLINE set."""
    env = (os.environ.get("HF_HUB_OFFLINE") or os.environ.get("TRANSFORMERS_OFFLINE") or "").strip().lower()
    return bool(offline) or env in _TRUE


def model_or_default(model: str | Path | None, role: str) -> str | Path:
    """``model``, or the role's default hub id (:data:`DEFAULT_MODELS`) when it is empty or None."""
    if model is None or str(model).strip() == "":
        if role not in DEFAULT_MODELS:
            raise ValueError(f"unknown model role {role!r}; roles: {', '.join(DEFAULT_MODELS)}")
        return DEFAULT_MODELS[role]
    return model


def fetch_command(repo_id: str) -> str:
    """The shell command that puts ``repo_id`` into the standard cache (huggingface_hub's CLI)."""
    return f"hf download {repo_id}"


def resolve_model_folder(model: str | Path | None, role: str, *, offline: bool = False) -> Path:
    """The local folder holding the model of ``role``.

    Args:
        model: a folder written by ``save_pretrained``, a hub id (``org/name``), or ""/None for the
            role's default id.
        role: "detector", "keypoints", "masks" or "depth" (picks the default).
        offline: never download (also when HF_HUB_OFFLINE=1 is set).

    Returns:
        ``model`` itself when it is a folder, else the hub id's snapshot folder in the cache
        (downloaded first when missing and downloads are on).

    Raises:
        InputError: one line naming the folder or the id, the cache folder, and how to fetch it.
    """
    model = model_or_default(model, role)
    path = Path(model).expanduser()
    if path.is_dir():
        return path
    if path.exists():
        raise InputError(path, "is a file, not a model folder",
                         "pass the folder written by save_pretrained (config.json + model.safetensors) or a hub id")
    text = str(model)
    if not _HUB_ID.match(text):
        raise InputError(text, "no such model folder, and not a Hugging Face hub id (org/name)",
                         f"pass a model folder, or a hub id such as {DEFAULT_MODELS.get(role, 'org/name')}")
    return _snapshot(text, downloads_off(offline))


def _snapshot(repo_id: str, offline: bool) -> Path:
    """The cache snapshot folder of ``repo_id``, downloading it unless ``offline``."""
    hub = require("huggingface_hub", "perception")
    cache = hub_cache_dir()
    fetch = fetch_command(repo_id)
    if not offline:
        log.info("model %s: looking it up in the Hugging Face cache %s (downloading what is missing)", repo_id, cache)
    try:
        folder = hub.snapshot_download(repo_id, cache_dir=cache, local_files_only=offline,
                                       allow_patterns=list(WEIGHT_PATTERNS))
    except Exception as err:  # noqa: BLE001 - every failure of the hub client becomes the one line below
        reason = _reason(err, offline)
        if offline:
            where = "only partly in" if type(err).__name__ == "IncompleteSnapshotError" else "not in"
            raise InputError(
                repo_id, f"not a local folder, and {where} the Hugging Face cache {cache} while downloads are off "
                f"(--offline or HF_HUB_OFFLINE=1){reason}",
                f"on a connected machine run `{fetch}` and copy its cache folder here (or point HF_HUB_CACHE at it), "
                "run without --offline / HF_HUB_OFFLINE=1, or pass a local model folder",
            ) from err
        raise InputError(
            repo_id, f"not a local folder, and it could not be downloaded into the Hugging Face cache {cache}{reason}",
            f"check the id and the network, then fetch it with `{fetch}`; a gated or private model needs "
            "`hf auth login` first; or pass a local model folder",
        ) from err
    log.info("model %s: %s", repo_id, folder)
    return Path(folder)


def _reason(err: Exception, offline: bool) -> str:
    """A short ``: why`` / `` (why)`` for a hub client error, or "" when the message already says it.

    Offline, "not in the cache" needs no more words. Online, the hub client reports an unreachable
    Hub as "not in the cache" too, with the network error as its cause: that cause is the reason.
    """
    name = type(err).__name__
    if name in ("RepositoryNotFoundError", "GatedRepoError"):
        return ": no such repository on the Hub, or it is gated/private"
    if name in ("LocalEntryNotFoundError", "OfflineModeIsEnabled"):
        if offline or err.__cause__ is None:
            return ""
        err = err.__cause__
        name = type(err).__name__
    text = str(err).strip()
    first = text.splitlines()[0][:200] if text else ""
    return f" ({name}: {first})" if first else f" ({name})"
