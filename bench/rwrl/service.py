"""Starting a throwaway `safedice serve` (SQLite in a temp dir, a free port) and the service's
Python client (clients/python, imported from this checkout)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "clients" / "python" / "src"))

from safedice_client import Client  # noqa: E402


def find_binary(explicit: str | None = None) -> str:
    """--safedice, $SAFEDICE_BIN, target/release/safedice of this checkout, or `safedice` on PATH."""
    for candidate in (explicit, os.environ.get("SAFEDICE_BIN"),
                      str(HERE.parents[1] / "target" / "release" / "safedice")):
        if candidate and Path(candidate).is_file():
            return candidate
    found = shutil.which("safedice")
    if found:
        return found
    raise SystemExit("no safedice binary: build it (cargo build --release) or pass --safedice / set SAFEDICE_BIN")


class Server:
    """`safedice serve --bind 127.0.0.1:0 --data-dir <dir>`, its address read from its log."""

    def __init__(self, binary: str, data_dir: Path, log_path: Path, extra: list[str] | None = None):
        data_dir.mkdir(parents=True, exist_ok=True)
        self.log_path = log_path
        self._log = open(log_path, "w")
        env = dict(os.environ, SAFEDICE_LOG_FORMAT="pretty", NO_COLOR="1")
        env.pop("SAFEDICE_API_TOKEN", None)
        self.proc = subprocess.Popen(
            [binary, "serve", "--bind", "127.0.0.1:0", "--data-dir", str(data_dir), *(extra or [])],
            stdout=self._log, stderr=subprocess.STDOUT, env=env)
        self.url = self._wait_for_address()

    def _wait_for_address(self, timeout: float = 60.0) -> str:
        deadline = time.time() + timeout
        pattern = re.compile(r"local_addr=(\S+)")
        while time.time() < deadline:
            if self.proc.poll() is not None:
                raise SystemExit(f"safedice serve exited ({self.proc.returncode}); log: {self.log_path}")
            m = pattern.search(re.sub(r"\x1b\[[0-9;]*m", "", self.log_path.read_text()))
            if m:
                url = f"http://{m.group(1)}"
                try:
                    with urllib.request.urlopen(url + "/readyz", timeout=2) as r:
                        if r.status == 200:
                            return url
                except OSError:
                    pass
            time.sleep(0.2)
        raise SystemExit(f"safedice serve did not become ready in {timeout} s; log: {self.log_path}")

    def client(self) -> Client:
        return Client(self.url, token=None)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self._log.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
