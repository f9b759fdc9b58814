"""The viewer's web page, served offline: viser's client build with its one outside request (an analytics tag)
removed, cached per build. Used by :mod:`nerfuser_ns.viewer` when a viewer starts.
"""

from __future__ import annotations

import atexit
import hashlib
import os
import shutil
import tempfile
import threading
import warnings
from pathlib import Path
from typing import Any

from viser import infra

_client_root: Path | None = None
_client_root_lock = threading.Lock()


def _cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nerfuser_ns"


def offline_client_root(build_dir: Path) -> Path:
    """viser's client build with its analytics tag removed (viser 0.2.7's index.html loads Google's gtag.js, the
    only outside request the page makes). The other files are links into the installed package.

    Kept in ``~/.cache/nerfuser_ns/viser-client-<key>`` (reused by every process; a temporary folder if the cache is
    not writable), keyed by the build's path and page.
    """
    global _client_root
    with _client_root_lock:
        if _client_root is not None and (_client_root / "index.html").is_file():
            return _client_root
        html = (build_dir / "index.html").read_text()
        start = html.find("<!-- Google tag (gtag.js) -->")
        end = html.find("</script>", html.find("</script>", start) + 1) if start >= 0 else -1
        if start < 0 or end < 0:
            return build_dir  # another viser build: nothing to remove
        key = hashlib.sha256(f"{build_dir.resolve()}\n{html}".encode()).hexdigest()[:16]
        root = _cache_dir() / f"viser-client-{key}"
        if not (root / "index.html").is_file():
            try:
                root.parent.mkdir(parents=True, exist_ok=True)
                tmp = Path(tempfile.mkdtemp(prefix=".viser-client-", dir=root.parent))
            except OSError:
                tmp = root = Path(tempfile.mkdtemp(prefix="nerfuser-viser-client-"))
                atexit.register(shutil.rmtree, root, True)
            for entry in build_dir.iterdir():
                if entry.name != "index.html":
                    (tmp / entry.name).symlink_to(entry.resolve())
            (tmp / "index.html").write_text(html[:start] + html[end + len("</script>") :])
            if tmp != root:
                try:
                    tmp.rename(root)
                except OSError:  # another process made it first
                    shutil.rmtree(tmp, ignore_errors=True)
        _client_root = root
        return root


def serve_offline_page() -> None:
    """Make every viser server of this process serve :func:`offline_client_root` (idempotent)."""

    init = infra.WebsockServer.__init__
    if getattr(init, "_nerfuser_offline", False):
        return

    def patched(self, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        root = self._http_server_root
        if root is not None and (Path(root) / "index.html").is_file():
            try:
                self._http_server_root = offline_client_root(Path(root))
            except OSError as e:  # a read-only temp dir: serve the page as it is
                warnings.warn(f"nerfuser viewer: serving viser's page unchanged ({e})", stacklevel=2)

    patched._nerfuser_offline = True  # type: ignore[attr-defined]
    infra.WebsockServer.__init__ = patched  # type: ignore[method-assign]
