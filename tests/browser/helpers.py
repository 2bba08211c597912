"""Helpers of ``tests/browser/test_browser.py``: a headless JupyterLab server and a headless Chromium.

The browser test proves, in a real browser, that the kit's interactive pictures work for a
student: each notebook that shows a plotly figure or an ipywidget is opened in JupyterLab, all
its cells are run, and the figures and widgets are inspected in the page (see the test's
docstring). Nothing here downloads anything: Chromium is the system's (Debian's ``chromium``
package, ``/usr/bin/chromium``), driven by the ``playwright`` Python package through its
``executable_path`` option.

* :func:`find_chromium` -- the Chromium executable, or ``None``.
* :func:`notebook_inventory` -- which notebooks show plotly figures / widgets, from their stored outputs.
* :class:`LabServer` -- JupyterLab on a free loopback port with a random token, in a throw-away
  root folder holding copies of the notebooks (the committed files are never touched).
* :func:`launch_browser` -- Playwright + Chromium with the flags this machine needs.
* :data:`LAB_JS` -- JavaScript run in the page against ``window.jupyterapp``.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
# COURSE_LIB_BROWSER_NOTEBOOK_DIR: another folder of notebooks (to prove the test fails on broken ones)
NOTEBOOKS_DIR = Path(os.environ.get("COURSE_LIB_BROWSER_NOTEBOOK_DIR") or REPO_ROOT / "notebooks")
SCREENSHOT_DIR = REPO_ROOT / "outputs" / "screenshots"  # git-ignored (outputs/)

PLOTLY_MIME = "application/vnd.plotly.v1+json"
WIDGET_MIME = "application/vnd.jupyter.widget-view+json"

# Flags for Chromium here: no GPU, no sandbox (root in CI), and no background connections (the
# machine's closed network refuses them, which would fill the console with errors).
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
]

# Lab settings of the test server (a throw-away user-settings folder): no autosave (the copies are
# throw-away anyway), every cell attached to the DOM (JupyterLab 4 otherwise detaches cells
# outside the viewport, so figures below the fold would not be drawn), no news/update requests.
LAB_SETTINGS = {
    "@jupyterlab/docmanager-extension/plugin.jupyterlab-settings": {"autosave": False},
    "@jupyterlab/notebook-extension/tracker.jupyterlab-settings": {"windowingMode": "none"},
    "@jupyterlab/apputils-extension/notification.jupyterlab-settings": {"fetchNews": "false", "checkForUpdates": False},
}


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome executable: ``$COURSE_LIB_CHROMIUM``, else the usual names on PATH."""
    env = os.environ.get("COURSE_LIB_CHROMIUM")
    if env:
        return env if Path(env).exists() else None
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class NotebookInfo:
    """What a notebook's stored outputs show: counts of plotly figures and widget views."""

    path: Path
    n_plotly: int = 0
    n_widgets: int = 0
    n_sliders: int = 0  # widget views with a slider (the kit's widgets; not e.g. tqdm's progress bars)
    n_errors: int = 0
    error_cells: list = field(default_factory=list)

    @property
    def interactive(self) -> bool:
        return self.n_plotly > 0 or self.n_widgets > 0


def notebook_inventory(folder: Path = NOTEBOOKS_DIR) -> list[NotebookInfo]:
    """One :class:`NotebookInfo` per ``folder/*.ipynb`` (sorted), read from the stored outputs."""
    infos = []
    for path in sorted(Path(folder).glob("*.ipynb")):
        nb = json.loads(path.read_text(encoding="utf-8"))
        info = NotebookInfo(path)
        for k, cell in enumerate(nb.get("cells", [])):
            for out in cell.get("outputs", []) if cell.get("cell_type") == "code" else []:
                if out.get("output_type") == "error":
                    info.n_errors += 1
                    info.error_cells.append(k)
                data = out.get("data", {})
                info.n_plotly += PLOTLY_MIME in data
                info.n_widgets += WIDGET_MIME in data
                text = data.get("text/plain", "")
                info.n_sliders += WIDGET_MIME in data and "Slider(" in ("".join(text) if isinstance(text, list) else text)
        infos.append(info)
    return infos


class LabServer:
    """JupyterLab 4 on ``127.0.0.1:<free port>`` with a random token, serving copies of notebooks.

    Use as a context manager. The kernels get ``COURSE_LIB_QUICK=1`` (short NeRF training) and no
    ``MPLBACKEND`` (so matplotlib uses the notebook's inline backend, as for a student).
    ``url(name)`` opens notebook ``name`` in its own workspace (parallel tabs do not share state).
    """

    def __init__(self, notebooks: list[Path], startup_timeout: float = 90.0):
        self.notebooks = [Path(p) for p in notebooks]
        self.startup_timeout = startup_timeout
        self.port = free_port()
        self.token = secrets.token_hex(16)
        self.tmp = Path(tempfile.mkdtemp(prefix="course-lib-lab-"))
        self.root = self.tmp / "notebooks"
        self.log_path = self.tmp / "jupyterlab.log"
        self.proc: subprocess.Popen | None = None

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def url(self, name: str) -> str:
        ws = "t-" + "".join(c if c.isalnum() else "-" for c in Path(name).stem)
        return f"{self.base}/lab/workspaces/{ws}/tree/{name}?reset&token={self.token}"

    def _write_settings(self) -> Path:
        settings = self.tmp / "user-settings"
        for rel, value in LAB_SETTINGS.items():
            f = settings / rel
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_text(json.dumps(value))
        return settings

    def __enter__(self) -> "LabServer":
        self.root.mkdir(parents=True)
        for p in self.notebooks:
            shutil.copy2(p, self.root / p.name)
        settings = self._write_settings()
        (self.tmp / "workspaces").mkdir()
        env = {k: v for k, v in os.environ.items() if k not in ("MPLBACKEND", "JUPYTER_TOKEN")}
        env.update(
            COURSE_LIB_QUICK="1",
            JUPYTER_CONFIG_DIR=str(self.tmp / "config"),
            JUPYTER_RUNTIME_DIR=str(self.tmp / "runtime"),
            JUPYTER_PLATFORM_DIRS="1",
            PYTHONUNBUFFERED="1",
        )
        cmd = [
            sys.executable, "-m", "jupyterlab",
            "--no-browser",
            "--ServerApp.ip=127.0.0.1",
            f"--ServerApp.port={self.port}",
            "--ServerApp.port_retries=0",
            f"--IdentityProvider.token={self.token}",
            f"--ServerApp.root_dir={self.root}",
            "--ServerApp.allow_remote_access=False",
            "--LabApp.expose_app_in_browser=True",
            f"--LabApp.user_settings_dir={settings}",
            f"--LabApp.workspaces_dir={self.tmp / 'workspaces'}",
            "--LabApp.extension_manager=readonly",
            "--LabApp.news_url=",
        ]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            cmd.append("--allow-root")  # CI runs as root
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._log, stderr=subprocess.STDOUT, cwd=self.root)
        deadline = time.monotonic() + self.startup_timeout
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"JupyterLab exited with code {self.proc.returncode}:\n{self.log_tail()}")
            try:
                with urllib.request.urlopen(f"{self.base}/api/status?token={self.token}", timeout=2) as r:
                    if r.status == 200:
                        return self
            except OSError:
                pass
            if time.monotonic() > deadline:
                self.__exit__(None, None, None)
                raise RuntimeError(f"JupyterLab did not answer within {self.startup_timeout:.0f} s:\n{self.log_tail()}")
            time.sleep(0.25)

    def log_tail(self, n: int = 40) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def __exit__(self, *exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            try:  # shut down kernels and server cleanly, then make sure
                req = urllib.request.Request(f"{self.base}/api/shutdown?token={self.token}", method="POST")
                urllib.request.urlopen(req, timeout=5).close()
                self.proc.wait(timeout=15)
            except Exception:
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
        if getattr(self, "_log", None):
            self._log.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


def launch_browser(playwright, chromium: str):
    """Headless Chromium (a fresh temporary profile) with the machine's flags; use ``new_context``."""
    return playwright.chromium.launch(executable_path=chromium, headless=True, args=CHROMIUM_FLAGS)


def new_context(browser, offline: bool = False, viewport=(1280, 900)):
    """A browser context of its own (own storage: JupyterLab tabs do not see each other).

    Generous default limits: on a loaded 2-core CI machine, six JupyterLab tabs starting at once
    take a while; every wait in the test is on a condition, so long limits cost nothing when
    things go well.
    """
    ctx = browser.new_context(offline=offline, viewport={"width": viewport[0], "height": viewport[1]})
    ctx.set_default_navigation_timeout(180_000)
    ctx.set_default_timeout(120_000)
    return ctx


# JavaScript helpers evaluated in a JupyterLab page (window.jupyterapp is exposed by the server).
LAB_JS = {
    # resolves once the notebook is open and its kernel is ready
    "ready": """async (name) => {
        for (let i = 0; i < 1200 && !window.jupyterapp; i++) await new Promise(r => setTimeout(r, 100));
        const app = window.jupyterapp;
        if (!app) return {error: 'window.jupyterapp is missing (JupyterLab did not start in the page)'};
        await app.started; await app.restored;
        let panel = null;  // up to 240 s: ten tabs open at once, and a loaded 2-core runner needed more than 120
        for (let i = 0; i < 2400; i++) {
            panel = app.shell.currentWidget;
            if (panel && panel.sessionContext && panel.context && panel.context.path.endsWith(name)) break;
            panel = null;
            await new Promise(r => setTimeout(r, 100));
        }
        if (!panel) return {error: 'notebook ' + name + ' did not open'};
        const late = new Promise(r => setTimeout(() => r('late'), 180000));
        if (await Promise.race([panel.context.ready.then(() => panel.sessionContext.ready), late]) === 'late')
            return {error: 'the kernel of ' + name + ' did not start within 180 s'};
        const k = panel.sessionContext.session && panel.sessionContext.session.kernel;
        return {path: panel.context.path, kernel: k ? k.name : null};
    }""",
    # starts "Run All Cells" (the Run menu's command) without waiting; the promise is kept
    "run_all": """() => {
        const app = window.jupyterapp;
        window.__kitRunAll = app.commands.execute('notebook:run-all-cells')
            .then(ok => (window.__kitRunAllDone = {ok: ok}))
            .catch(e => (window.__kitRunAllDone = {ok: false, error: String(e)}));
        return true;
    }""",
    # state of the run: done flag, kernel status, executed/total code cells, errors in outputs
    "state": """() => {
        const panel = window.jupyterapp.shell.currentWidget;
        const cells = panel.content.model.cells;
        let total = 0, executed = 0; const errors = [];
        for (let i = 0; i < cells.length; i++) {
            const c = cells.get(i);
            if (c.type !== 'code') continue;
            if (!c.sharedModel.getSource().trim()) continue;  // JupyterLab does not number empty cells
            total += 1;
            if (c.executionCount !== null) executed += 1;
            const outs = c.outputs.toJSON();
            for (const o of outs) if (o.output_type === 'error') errors.push({cell: i, ename: o.ename, evalue: o.evalue});
        }
        const k = panel.sessionContext.session && panel.sessionContext.session.kernel;
        return {done: window.__kitRunAllDone || null, status: k ? k.status : 'none', total, executed, errors};
    }""",
    # per plotly figure in the page: what it drew
    "plots": """() => Array.from(document.querySelectorAll('.js-plotly-plot')).map((el, i) => ({
        index: i,
        traces: el._fullData ? el._fullData.length : 0,
        types: el._fullData ? Array.from(new Set(el._fullData.map(t => t.type))) : [],
        points: el._fullData ? el._fullData.reduce((n, t) => n + (t.x ? t.x.length : 0), 0) : 0,
        gl_canvas: !!el.querySelector('.gl-container canvas'),
        svg: !!el.querySelector('.svg-container'),
        in_widget: !!el.closest('.jupyter-widgets, .widget-output'),
        no_webgl: (el.innerText || '').includes('WebGL is not supported'),
        width: el.getBoundingClientRect().width, height: el.getBoundingClientRect().height,
    }))""",
}
