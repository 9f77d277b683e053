"""Where a Zero-1-to-3 checkpoint comes from: a local directory, or a Hugging Face Hub id fetched on demand.

:func:`resolve_checkpoint` turns what a user passes to
:meth:`~lightning_vtr.synthesis.zero123.Zero123Synthesizer.from_pretrained` into a local folder. A Hub id
(``"owner/name"``) is looked up in the Hub cache, and, when online, only the files the synthesizer reads are
downloaded (configs plus one set of weights per component: no original ``.ckpt``, no second precision).
``HF_HUB_OFFLINE`` is read at call time. ``huggingface_hub`` is imported only for Hub ids.
"""

from __future__ import annotations

import os
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

from lightning_vtr.synthesis.zero123_checkpoint import (
    COMPONENT_KINDS,
    LDM_SUFFIXES,
    OPTIONAL_FOLDERS,
    PROJECTION_LAYOUTS,
    Zero123CheckpointError,
    checkpoint_name,
    ldm_checkpoint_error,
    select_weight_files,
)

__all__ = ["CheckpointSource", "download_command", "hub_offline", "is_hub_id", "resolve_checkpoint", "select_hub_files"]

_HUB_ID = re.compile(r"^[A-Za-z0-9][\w.\-]*/[A-Za-z0-9][\w.\-]*$")
_COMMIT = re.compile(r"^[0-9a-f]{40}$")
#: what `hf download` needs to fetch every folder the synthesizer may read
_INCLUDE = ("model_index.json", *(f"{sub}/*" for sub in (*COMPONENT_KINDS, *PROJECTION_LAYOUTS, *OPTIONAL_FOLDERS)))


@dataclass(frozen=True)
class CheckpointSource:
    """A checkpoint resolved to a local folder.

    Attributes:
        folder: the directory holding ``unet/``, ``vae/``, ...
        name: what the checkpoint is called (``"owner/name"`` for a Hub id, else the folder name); the pose
            rule reads it.
        ident: a stable identity for cache keys: the resolved folder, or ``"owner/name@<commit>"``.
        hint: for a Hub id, the command that fetches missing files (added to loading errors); else ``""``.
    """

    folder: Path
    name: str
    ident: str
    hint: str = ""


def is_hub_id(value: str) -> bool:
    """Whether ``value`` reads as a Hub model id ``"owner/name"`` (callers check local paths first)."""
    return bool(_HUB_ID.match(value)) and ".." not in value and not value.endswith(LDM_SUFFIXES)


def hub_offline() -> bool:
    """``HF_HUB_OFFLINE`` (or ``TRANSFORMERS_OFFLINE``) as set now; ``huggingface_hub`` reads it only at import."""
    for var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"):
        value = os.environ.get(var)
        if value is not None and value.strip() != "":
            return value.strip().upper() in ("1", "ON", "YES", "TRUE")
    from huggingface_hub import constants

    return bool(constants.HF_HUB_OFFLINE)


def download_command(repo_id: str, revision: str | None = None, cache_dir: str | os.PathLike | None = None) -> str:
    """The shell command that puts what :func:`resolve_checkpoint` needs of ``repo_id`` into the Hub cache."""
    parts = ["hf", "download", repo_id]
    if revision is not None:
        parts += ["--revision", revision]
    if cache_dir is not None:
        parts += ["--cache-dir", str(cache_dir)]
    parts += ["--include", *_INCLUDE]
    return " ".join(shlex.quote(p) for p in parts)


def select_hub_files(files: list[str], variant: str | None, where: str) -> list[str]:
    """The files of a Hub repository listing that the synthesizer reads, one weight set per component.

    Args:
        files: every path in the repository (``"unet/config.json"``, ...).
        variant: as for :meth:`~lightning_vtr.synthesis.zero123.Zero123Synthesizer.from_pretrained`.
        where: the repository as it should appear in messages.

    Raises:
        Zero123CheckpointError: a component is missing from the repository (every one listed).
    """
    by_folder: dict[str, list[str]] = {}
    for path in files:
        folder, _, name = path.rpartition("/")
        if folder and "/" not in folder:
            by_folder.setdefault(folder, []).append(name)
    selected = [f for f in files if f == "model_index.json"]
    problems = []

    def component(sub: str, kind: str) -> None:
        names = by_folder.get(sub, [])
        if "config.json" not in names:
            problems.append(f"{sub}/: expected config.json; {f'found {sorted(names)}' if names else 'folder missing'}")
            return
        try:
            weights = select_weight_files(names, kind, variant, f"{sub}/")
        except Zero123CheckpointError as err:
            problems.append(str(err))
            return
        # a sharded set brings its index and every shard of the same variant
        selected.extend(f"{sub}/{name}" for name in ("config.json", *weights.files))

    for sub, kind in COMPONENT_KINDS.items():
        component(sub, kind)
    layouts = [sub for sub in PROJECTION_LAYOUTS if sub in by_folder]
    if layouts:
        component(layouts[0], "diffusers")
    else:
        problems.append("cc_projection/ or clip_camera_projection/: expected the camera projection; neither exists")
    for sub, config in OPTIONAL_FOLDERS.items():
        if config in by_folder.get(sub, []):
            selected.append(f"{sub}/{config}")
    if problems:
        top = sorted({p.split("/", 1)[0] + "/" if "/" in p else p for p in files})
        hint = ""
        ckpts = [f for f in files if f.endswith(LDM_SUFFIXES)]
        if ckpts:
            hint = (
                f"\nIt holds original latent-diffusion checkpoints {ckpts}: download one, convert it to the diffusers "
                "format (passing the .ckpt file to from_pretrained prints the command) and pass the output folder."
            )
        raise Zero123CheckpointError(
            f"{where} is not a diffusers-format Zero-1-to-3 checkpoint (top level has {top}):\n  - "
            + "\n  - ".join(problems)
            + hint
        )
    return list(dict.fromkeys(selected))


def _cache_root(cache_dir: str | os.PathLike | None) -> Path:
    if cache_dir is not None:
        return Path(cache_dir)
    from huggingface_hub import constants

    return Path(constants.HF_HUB_CACHE)


def cached_snapshot(repo_id: str, revision: str | None, cache_dir: str | os.PathLike | None) -> Path | None:
    """The Hub cache's snapshot folder of ``repo_id`` at ``revision`` (branch, tag or commit), if present."""
    repo = _cache_root(cache_dir) / f"models--{repo_id.replace('/', '--')}"
    revision = revision or "main"
    commit = revision if _COMMIT.match(revision) else None
    ref = repo / "refs" / revision
    if commit is None and ref.is_file():
        commit = ref.read_text().strip()
    if commit is None:
        return None
    snapshot = repo / "snapshots" / commit
    return snapshot if snapshot.is_dir() else None


# the two calls that reach the network; tests replace them
def _list_repo_files(repo_id: str, revision: str | None, token: str | bool | None) -> list[str]:
    from huggingface_hub import list_repo_files

    return list_repo_files(repo_id, revision=revision, token=token)


def _snapshot_download(
    repo_id: str,
    revision: str | None,
    cache_dir: str | os.PathLike | None,
    token: str | bool | None,
    allow_patterns: list[str],
) -> str:
    from huggingface_hub import snapshot_download

    return snapshot_download(
        repo_id,
        revision=revision,
        cache_dir=None if cache_dir is None else os.fspath(cache_dir),
        token=token,
        allow_patterns=allow_patterns,
    )


def _not_found(repo_id: str, revision: str | None, cache_dir: str | os.PathLike | None, why: str) -> FileNotFoundError:
    return FileNotFoundError(
        f"`path` {repo_id!r} is neither a local directory nor a Zero-1-to-3 checkpoint in the Hugging Face Hub cache "
        f"({_cache_root(cache_dir)}, revision {revision or 'main'!r}): {why}. Fetch it with\n"
        f"    {download_command(repo_id, revision, cache_dir)}\n"
        "(`huggingface-cli download` with the same arguments on huggingface_hub < 0.34), or download the "
        "folder elsewhere and pass its path."
    )


def _hub_source(
    repo_id: str,
    *,
    revision: str | None,
    cache_dir: str | os.PathLike | None,
    token: str | bool | None,
    local_files_only: bool,
    variant: str | None,
) -> CheckpointSource:
    offline = local_files_only or hub_offline()
    reason = "HF_HUB_OFFLINE is set" if hub_offline() else "local_files_only=True"
    if not offline:
        from huggingface_hub.utils import GatedRepoError, RepositoryNotFoundError, RevisionNotFoundError

        try:
            files = _list_repo_files(repo_id, revision, token)
        except GatedRepoError as err:
            raise FileNotFoundError(
                f"`path` {repo_id!r} is a gated Hub repository: accept its terms on the Hub and log in "
                f"(`hf auth login`) or pass `token=` ({type(err).__name__})"
            ) from err
        except RevisionNotFoundError as err:
            raise FileNotFoundError(
                f"`revision` must name a branch, tag or commit of {repo_id!r}, got {revision or 'main'!r}"
            ) from err
        except RepositoryNotFoundError as err:
            raise FileNotFoundError(
                f"`path` {repo_id!r} is neither a local directory nor a Hub repository (not found, or private: "
                "log in with `hf auth login` or pass `token=`)"
            ) from err
        except Exception as err:
            offline, reason = True, f"the Hub could not be reached ({type(err).__name__}: {err})"
        else:
            where = f"{repo_id!r} (revision {revision or 'main'!r})"
            wanted = select_hub_files(files, variant, where)
            folder = Path(_snapshot_download(repo_id, revision, cache_dir, token, wanted))
    if offline:
        snapshot = cached_snapshot(repo_id, revision, cache_dir)
        if snapshot is None:
            raise _not_found(repo_id, revision, cache_dir, f"not cached, and {reason}")
        folder = snapshot
    return CheckpointSource(
        folder=folder,
        name=repo_id,
        ident=f"{repo_id}@{folder.name}",
        hint=f"Fetch what is missing with\n    {download_command(repo_id, revision, cache_dir)}",
    )


def resolve_checkpoint(
    path: str | os.PathLike,
    *,
    revision: str | None = None,
    cache_dir: str | os.PathLike | None = None,
    token: str | bool | None = None,
    local_files_only: bool = False,
    variant: str | None = None,
) -> CheckpointSource:
    """A local directory as is; a Hub id from the cache or, when online, downloaded (needed files only).

    Args:
        path: a checkpoint directory, or a Hub id ``"owner/name"`` that is not a local path.
        revision: Hub branch, tag or commit (default ``"main"``); ignored for a local directory.
        cache_dir: Hub cache directory (default: ``huggingface_hub``'s, ``HF_HUB_CACHE``).
        token: Hub token for private or gated repositories.
        local_files_only: never reach the network (as ``HF_HUB_OFFLINE=1``).
        variant: weight variant to download (see :func:`select_weight_files`).

    Raises:
        Zero123CheckpointError: ``path`` is an original latent-diffusion ``.ckpt`` (the message says how to
            convert it), or the Hub repository holds no diffusers-format Zero-1-to-3 checkpoint.
        FileNotFoundError: ``path`` does not exist and is not a Hub id, or the id is not cached and cannot be
            downloaded (offline, unknown, gated); the message names the id and the command that fetches it.
    """
    local = Path(path)
    if local.is_dir():
        return CheckpointSource(folder=local, name=checkpoint_name(local), ident=str(local.resolve()))
    if local.suffix.lower() in LDM_SUFFIXES:
        if local.is_file():
            raise ldm_checkpoint_error(local)
        raise FileNotFoundError(
            f"`path` must be a Zero-1-to-3 checkpoint directory, got the missing file {str(path)!r}"
        )
    if local.exists():
        raise FileNotFoundError(f"`path` must be a Zero-1-to-3 checkpoint directory, got the file {str(path)!r}")
    if isinstance(path, str) and is_hub_id(path):
        return _hub_source(
            path,
            revision=revision,
            cache_dir=cache_dir,
            token=token,
            local_files_only=local_files_only,
            variant=variant,
        )
    raise FileNotFoundError(
        f"`path` must be a Zero-1-to-3 checkpoint directory or a Hub id 'owner/name', got {str(path)!r} "
        "(no such directory)"
    )
