"""Where stores live: local paths, ``file://`` URLs and any other fsspec URL (``memory://``,
``s3://``, ``gs://``...).

This is the one place that turns what a user gives as a store location (a path or a URL,
plus an optional ``storage_options`` dict) into what zarr and xarray need, and that checks,
lists and deletes there. Local paths and ``file://`` URLs stay plain paths, on the local
code paths (rename for atomic outputs, xstack's direct chunk writer); everything else goes
through an fsspec filesystem.

A protocol is configured the protocol's own way: s3fs (botocore) honours
``AWS_ENDPOINT_URL``, credentials and profiles; fsspec's configuration
(``FSSPEC_<PROTOCOL>_<OPTION>`` variables such as ``FSSPEC_S3_ENDPOINT_URL``, or its config
files) is applied too. Explicit ``storage_options`` win over both. Where a function is
called without ``storage_options`` (e.g. a stage opening its input), the ones set by
:func:`use_storage_options` apply: the command line sets ``--storage-options`` that way.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from xstack.errors import XstackError

#: Protocols that are the local filesystem.
LOCAL_PROTOCOLS = frozenset({"file", "local"})

_DEFAULT_OPTIONS: contextvars.ContextVar[dict[str, Any] | None] = contextvars.ContextVar(
    "xstack_storage_options", default=None)


@contextlib.contextmanager
def use_storage_options(options: Mapping[str, Any] | None) -> Iterator[None]:
    """Within the block, ``options`` apply to every URL opened or written without explicit
    ``storage_options`` (``None``: nothing changes).

    Parameters
    ----------
    options
        fsspec storage options, e.g. ``{"endpoint_url": "http://localhost:9000", "anon": True}``
        for ``s3://`` (the keyword arguments of the protocol's filesystem class).
    """
    if options is None:
        yield
        return
    token = _DEFAULT_OPTIONS.set(check_storage_options(options))
    try:
        yield
    finally:
        _DEFAULT_OPTIONS.reset(token)


def check_storage_options(options: Any) -> dict[str, Any]:
    """``options`` as a plain dict with string keys, or an :class:`XstackError`."""
    if options is None:
        return {}
    if not isinstance(options, Mapping) or not all(isinstance(k, str) for k in options):
        raise XstackError("storage_options must be a dict of option name to value, got "
                          f"{type(options).__name__}", option="storage_options")
    return dict(options)


def is_url(path: Any) -> bool:
    """True if ``path`` is a URL (``protocol://...`` or a chained ``a::b://...``), not a path."""
    return isinstance(path, str) and ("://" in path or "::" in path)


def is_remote(path: Any) -> bool:
    """True if ``path`` is a URL of another filesystem than the local one."""
    return is_url(path) and _protocol(path) not in LOCAL_PROTOCOLS


def _protocol(url: str) -> str:
    # the outermost protocol of a chained URL ("simplecache::s3://b/k") is the one written
    # last; the one that names the data is the innermost
    inner = url.split("::")[-1]
    return inner.split("://", 1)[0].lower() if "://" in inner else "file"


def _options(protocol: str, storage_options: Mapping[str, Any] | None) -> dict[str, Any]:
    """The options of a filesystem: fsspec's configuration (read now, so that variables set
    after fsspec was imported count), then the given or default ``storage_options``."""
    import fsspec.config

    env: dict[str, dict[str, Any]] = {}
    fsspec.config.set_conf_env(env)
    explicit = storage_options if storage_options is not None else _DEFAULT_OPTIONS.get()
    return {**fsspec.config.conf.get(protocol, {}), **env.get(protocol, {}),
            **check_storage_options(explicit)}


def _filesystem_class(url: str, protocol: str) -> None:
    """Check that fsspec knows ``protocol`` and its package is installed (one-line error)."""
    import fsspec
    from fsspec.registry import known_implementations

    try:
        fsspec.get_filesystem_class(protocol)
    except ValueError:
        raise XstackError(f"{url}: unknown storage protocol {protocol!r} (no fsspec filesystem "
                          "implements it)") from None
    except ImportError:
        package = known_implementations.get(protocol, {}).get("class", protocol).split(".")[0]
        hint = "pip install 'xstack[s3]'" if package == "s3fs" else f"pip install {package}"
        raise XstackError(f"{url}: {protocol}:// URLs need the package {package} ({hint})") from None


@dataclass(frozen=True)
class Location:
    """A store location: a local path, or a path on an fsspec filesystem.

    Attributes
    ----------
    url : str
        What the user gave (a path or a URL), for messages and provenance.
    path : str
        The local path (``file://`` stripped), or the path on ``fs`` (no protocol).
    fs : fsspec.AbstractFileSystem or None
        The filesystem of a remote location; None for a local one.
    options : dict
        The storage options ``fs`` was made with (remote only).
    """

    url: str
    path: str
    fs: Any = None
    protocol: str = "file"
    options: dict[str, Any] = field(default_factory=dict, repr=False)

    def __str__(self) -> str:
        return self.url

    @property
    def name(self) -> str:
        """The location in messages: the normalised local path, or the URL."""
        return str(Path(self.path)) if self.fs is None else self.url

    @property
    def local(self) -> bool:
        """True for the local filesystem (plain paths and ``file://`` URLs)."""
        return self.fs is None

    @property
    def local_path(self) -> Path:
        """The local path (only for a local location)."""
        if self.fs is not None:
            raise XstackError(f"{self.url}: not a local path")
        return Path(self.path)

    def join(self, name: str) -> Location:
        """The location of ``name`` inside this one (a sibling's name for an atomic write)."""
        if self.fs is None:
            child = str(Path(self.path) / name)
            return Location(child, child)
        return Location(f"{self.url.rstrip('/')}/{name}", f"{self.path.rstrip('/')}/{name}",
                        self.fs, self.protocol, self.options)

    def exists(self) -> bool:
        """True if anything (file, directory, any key under the prefix) is at this location."""
        if self.fs is None:
            p = Path(self.path)
            return p.exists() or p.is_symlink()
        # listings are cached by fsspec filesystems; another writer may have changed them
        self.fs.invalidate_cache(self.path)
        return bool(self.fs.exists(self.path))

    def isdir(self) -> bool:
        """True if this is a directory (a prefix with keys under it, on an object store)."""
        if self.fs is None:
            return Path(self.path).is_dir()
        self.fs.invalidate_cache(self.path)
        return bool(self.fs.isdir(self.path))

    def parent_exists(self) -> bool:
        """True if a new output can be created here: the parent directory exists locally, the
        bucket on an object store (whose directories need not be created)."""
        if self.fs is None:
            return Path(self.path).parent.exists()
        split = getattr(self.fs, "split_path", None)
        if split is None:
            return True
        bucket = split(self.path)[0]
        self.fs.invalidate_cache(bucket)
        return bool(self.fs.exists(bucket))

    def remove(self) -> None:
        """Delete whatever is at this location (no error if there is nothing)."""
        if self.fs is None:
            import shutil

            p = Path(self.path)
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            return
        if self.exists():
            self.fs.rm(self.path, recursive=True)
            self.fs.invalidate_cache(self.path)

    def listdir(self) -> list[tuple[str, bool]]:
        """``(name, is_directory)`` of every entry directly inside this location, sorted."""
        if self.fs is None:
            return sorted((p.name, p.is_dir()) for p in Path(self.path).iterdir())
        self.fs.invalidate_cache(self.path)
        entries = self.fs.ls(self.path, detail=True)
        return sorted((e["name"].rstrip("/").rsplit("/", 1)[-1], e.get("type") == "directory")
                      for e in entries)

    def read_bytes(self, name: str = "") -> bytes:
        """The bytes of the file ``name`` inside this location (or of this location itself)."""
        target = self.join(name) if name else self
        if self.fs is None:
            return Path(target.path).read_bytes()
        return bytes(self.fs.cat_file(target.path))

    def read_many(self, names: list[str]) -> dict[str, bytes]:
        """The bytes of the files ``names`` inside this location that exist (one batch of
        requests on a remote filesystem)."""
        if self.fs is None:
            out = {}
            for name in names:
                with contextlib.suppress(FileNotFoundError, NotADirectoryError):
                    out[name] = (Path(self.path) / name).read_bytes()
            return out
        full = {f"{self.path.rstrip('/')}/{n}": n for n in names}
        got = self.fs.cat(list(full), on_error="omit")
        return {full[k]: bytes(v) for k, v in got.items() if k in full}

    def write_many(self, files: Mapping[str, bytes]) -> None:
        """Write the files ``files`` (relative name -> bytes) inside this location."""
        if self.fs is None:
            for name, data in files.items():
                target = Path(self.path) / name
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(data)
            return
        self.fs.pipe({f"{self.path.rstrip('/')}/{k}": bytes(v) for k, v in files.items()})

    def zarr_store(self, read_only: bool = False) -> Any:
        """What zarr and xarray open: the local path (a string), or a
        :class:`zarr.storage.FsspecStore` on this location."""
        if self.fs is None:
            return self.path
        from zarr.storage import FsspecStore

        url = self.url if not self.url.endswith("/") else self.url.rstrip("/")
        return FsspecStore.from_url(url, storage_options=self.options, read_only=read_only)


def locate(path: str | os.PathLike | Location, storage_options: Mapping[str, Any] | None = None
           ) -> Location:
    """The :class:`Location` of a path or URL.

    Parameters
    ----------
    path
        A local path, a ``file://`` URL, or any fsspec URL (``memory://``, ``s3://``...).
    storage_options
        Options of the URL's filesystem (e.g. ``{"endpoint_url": ..., "anon": True}`` for
        s3); default: those of :func:`use_storage_options`, if any. Ignored for local paths.

    Raises
    ------
    XstackError
        Unknown protocol, or its package (s3fs, gcsfs...) not installed: one line naming it.
    """
    if isinstance(path, Location):
        return path
    if not is_url(path):
        text = os.fspath(path)
        return Location(str(Path(text)) if isinstance(path, os.PathLike) else text, text)
    url = str(path)
    protocol = _protocol(url)
    if protocol in LOCAL_PROTOCOLS and "::" not in url:
        from fsspec.implementations.local import LocalFileSystem

        local = LocalFileSystem._strip_protocol(url)
        return Location(local, local)
    _filesystem_class(url, protocol)
    from fsspec.core import url_to_fs

    options = _options(protocol, storage_options)
    try:
        fs, fs_path = url_to_fs(url, **options)
    except (TypeError, ValueError) as exc:
        raise XstackError(f"{url}: bad storage options ({exc})", option="storage_options") from None
    return Location(url, fs_path, fs, protocol, options)


def output_path(path: str | os.PathLike | Location) -> Path | str:
    """What the writers return for an output: a :class:`~pathlib.Path` for a local one, the
    URL (a string) for a remote one."""
    if isinstance(path, Location):
        return Path(path.path) if path.local else path.url
    if is_remote(path):
        return str(path)
    return Path(locate(path).path)
