"""``omnirecon view``: serve a viewer bundle on 127.0.0.1 and open it in a browser."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import tyro

from omnirecon.viewer.server import HOST


@dataclass
class ViewCommand:
    """Serve the web viewer of an `omnirecon export` folder on 127.0.0.1 (only files inside the bundle
    folder are served) and open it in the default browser. Ctrl-C stops it."""

    folder: tyro.conf.Positional[Path]
    """The --out folder of `omnirecon export` (or its viewer/ subfolder)."""
    port: int = 8765
    """Port on 127.0.0.1 (0: any free port)."""
    browser: bool = True
    """Open the page in the default web browser (--no-browser: only print the URL)."""
    quiet: bool = False
    """Do not log requests."""

    def main(self) -> None:
        from omnirecon.viewer.server import ViewerServer, bundle_folder  # lazy: the HTTP server loads only when serving

        folder = bundle_folder(self.folder)
        server = ViewerServer(folder, self.port, quiet=self.quiet)
        url = server.url
        print(f"serving {folder} at {url} (only {HOST}; Ctrl-C to stop)", flush=True)
        if self.browser:
            import webbrowser

            try:
                webbrowser.open(url)
            except Exception:  # noqa: BLE001 - no browser is fine: the URL is printed
                pass
        try:
            server.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            server.server_close()
