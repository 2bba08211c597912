"""The notebooks' interactive pictures really render: JupyterLab + headless Chromium.

For every notebook in ``notebooks/`` whose stored outputs contain a plotly figure
(``application/vnd.plotly.v1+json``) or an ipywidget view, the session fixture

1. starts JupyterLab 4 headless on a free loopback port with a random token, serving throw-away
   copies of those notebooks, with ``COURSE_LIB_QUICK=1`` in the kernels' environment;
2. opens each notebook in its own tab of headless Chromium (all tabs at once, so the kernels run
   in parallel), waits for its kernel, and runs JupyterLab's "Run All Cells" command (the Run
   menu's entry);
3. waits until that command has finished, every code cell has an execution count and the
   kernel is idle, then inspects the page.

Then one test per notebook asserts that

* no cell raised (no ``error`` output);
* every plotly figure has drawn: at least as many ``.js-plotly-plot`` elements as the stored
  notebook has plotly outputs, each with traces, a WebGL canvas (3-D) or an SVG container (2-D),
  no "WebGL is not supported" message, and a screenshot of the plot area that is not blank;
* every widget view is alive: moving its (first) slider with the keyboard changes the widget's
  output (the last child of its box: the redrawn figure or image);
* the browser console shows no errors (and no uncaught page errors).

A last test runs ``python -m course_lib sfm`` and opens its ``scene.html`` from a ``file://`` URL
with the network cut off: plotly.js must be embedded and the 3-D scene must draw.

Screenshots (each plot, each widget before/after its slider moved, each page) go to
``outputs/screenshots/`` (git-ignored); the test prints where. The tests skip, saying why, only
when no Chromium executable is found (install Debian's ``chromium``, or set
``COURSE_LIB_CHROMIUM`` to a Chrome/Chromium binary). Nothing is downloaded.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.browser.helpers import (
    LAB_JS,
    REPO_ROOT,
    SCREENSHOT_DIR,
    LabServer,
    find_chromium,
    launch_browser,
    new_context,
    notebook_inventory,
)

#: Minutes, not seconds: left out of the quick subset (pytest -m "not slow").
pytestmark = pytest.mark.slow

CHROMIUM = find_chromium()
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None,
    reason="no Chromium found (apt-get install chromium, or set COURSE_LIB_CHROMIUM): the browser checks did not run",
)

INTERACTIVE = [info for info in notebook_inventory() if info.interactive]
if os.environ.get("COURSE_LIB_BROWSER_NOTEBOOKS"):  # e.g. "01,05": only these (while developing)
    _only = tuple(os.environ["COURSE_LIB_BROWSER_NOTEBOOKS"].split(","))
    INTERACTIVE = [info for info in INTERACTIVE if info.path.name.startswith(_only)]
RUN_TIMEOUT_S = float(os.environ.get("COURSE_LIB_BROWSER_TIMEOUT", "420"))  # all notebooks together
WIDGET_TIMEOUT_S = 60.0  # one slider move: rerun RANSAC, redraw a BA scene, render a NeRF view

# Console messages that are not errors of the kit. Keep this list short and explain each entry.
CONSOLE_ALLOW = (
    # none yet
)


def _console_line(msg) -> str:
    """``"error: <text> [<url>]"``: the URL says which resource failed ("Failed to load resource")."""
    url = (msg.location or {}).get("url", "")
    return f"{msg.type}: {msg.text}" + (f" [{url.split('?')[0]}]" if url else "")


def _server_hiccup(line: str) -> bool:
    """A 5xx answer of the Jupyter server's own REST API (sessions, contents, workspaces, settings).

    Under heavy load (eight notebooks starting kernels at once on 2 cores) the server can answer
    one of its own API calls with a 500; the page retries or carries on, and it says nothing about
    the notebooks. Reported, not failed. A 5xx on any other resource (a notebook's output, an
    extension's script) still fails.
    """
    url = line.rsplit(" [", 1)[1] if line.endswith("]") and " [" in line else ""  # as _console_line appends it
    return "status of 5" in line and "/api/" in url


def _playwright():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:  # Chromium is there but the pinned test package is not: an install error
        pytest.fail("the Python package 'playwright' is missing: pip install -r environment.txt "
                    "(it drives the system Chromium; no browser download is needed)")
    return sync_playwright


def _say(config, text: str) -> None:
    """Write a line to the terminal even when pytest captures output (where the screenshots are)."""
    reporter = config.pluginmanager.get_plugin("terminalreporter") if config is not None else None
    capman = config.pluginmanager.get_plugin("capturemanager") if config is not None else None
    if reporter is not None and capman is not None:
        with capman.global_and_fixture_disabled():
            reporter.write_line(text)
    else:
        print(text)


def _distinct_colours(png: bytes, crop=(0.3, 0.3, 0.7, 0.7)) -> int:
    """Number of distinct RGB colours in the central part of a PNG screenshot."""
    from PIL import Image

    img = Image.open(io.BytesIO(png)).convert("RGB")
    w, h = img.size
    box = (int(crop[0] * w), int(crop[1] * h), int(crop[2] * w), int(crop[3] * h))
    return len(img.crop(box).getcolors(maxcolors=1 << 20) or [])


# The widget views of a page: each top-level widget box of an output area (nested widgets and the
# output areas inside Output widgets excluded). They get a data-kit-widget index for locators.
WIDGET_ROOTS_JS = """() => {
    const roots = Array.from(document.querySelectorAll('.jp-OutputArea-output > .jupyter-widgets'))
        .filter(el => !el.parentElement.closest('.jupyter-widgets'));
    roots.forEach((el, i) => el.setAttribute('data-kit-widget', String(i)));
    return roots.length;
}"""

WIDGET_STATE_JS = """(i) => {
    const root = document.querySelector('[data-kit-widget="' + i + '"]');
    const handle = root && root.querySelector('.noUi-handle');
    const out = root && root.lastElementChild;  // the redrawn part: Output, Image or box of images
    return {
        handle: !!handle,
        value: handle ? handle.getAttribute('aria-valuenow') : null,
        max: handle ? handle.getAttribute('aria-valuemax') : null,
        output: out ? out.outerHTML : null,
        stderr: !!(out && out.querySelector('[data-mime-type="application/vnd.jupyter.stderr"]')),
    };
}"""


def _check_widgets(page, stem: str, shots: list[str]) -> tuple[int, int, list[str]]:
    """Move the first slider of every widget view; returns (views drawn, sliders alive, problems).

    Widget views without a slider (e.g. tqdm's progress bar) only have to be drawn.
    """
    problems: list[str] = []
    alive = 0
    n_views = page.evaluate(WIDGET_ROOTS_JS)
    for i in range(n_views):
        root = page.locator(f'[data-kit-widget="{i}"]')
        root.scroll_into_view_if_needed()
        before = page.evaluate(WIDGET_STATE_JS, i)
        if not before["handle"]:
            continue
        path = SCREENSHOT_DIR / f"{stem}_widget{i}_before.png"
        root.screenshot(path=str(path))
        shots.append(path.name)
        at_max = before["value"] is not None and before["max"] is not None and float(before["value"]) >= float(before["max"])
        handle = root.locator(".noUi-handle").first
        handle.focus()
        handle.press("ArrowLeft" if at_max else "ArrowRight")
        try:
            page.wait_for_function(
                """([i, before, value]) => {
                    const s = (%s)(i);
                    return s.value !== value && s.output !== null && s.output !== before && !s.stderr;
                }""" % WIDGET_STATE_JS,
                arg=[i, before["output"], before["value"]],
                timeout=WIDGET_TIMEOUT_S * 1000,
                polling=250,
            )
        except Exception:
            now = page.evaluate(WIDGET_STATE_JS, i)
            problems.append(f"widget {i}: moving the slider from {before['value']} (now {now['value']}) did not "
                            f"change its output within {WIDGET_TIMEOUT_S:.0f} s" + (" (stderr shown)" if now["stderr"] else ""))
            continue
        _wait_for_plots(page, root, 0)  # a plotly figure redrawn inside the widget must draw too
        path = SCREENSHOT_DIR / f"{stem}_widget{i}_after.png"
        root.screenshot(path=str(path))
        shots.append(path.name)
        alive += 1
    return n_views, alive, problems


def _wait_for_plots(page, scope, expected: int) -> None:
    """Wait until ``expected`` plotly figures (and all that are there) under ``scope`` have drawn."""
    try:
        page.wait_for_function(
            """([root, n]) => {
                const els = Array.from((root || document).querySelectorAll('.js-plotly-plot'));
                return els.length >= n && els.every(el => el._fullData && el._fullData.length > 0
                    && (el.querySelector('.gl-container canvas') || el.querySelector('.svg-container')));
            }""",
            arg=[scope.element_handle() if scope is not None else None, expected],
            timeout=60_000,
            polling=250,
        )
    except Exception:
        pass  # the caller reports what is there


def _check_plots(page, stem: str, expected: int, shots: list[str]) -> tuple[list[dict], list[str]]:
    """Wait for the plotly figures to draw; returns (per-plot info, problems)."""
    problems: list[str] = []
    _wait_for_plots(page, None, expected)
    plots = page.evaluate(LAB_JS["plots"])
    if len(plots) < expected:
        problems.append(f"{len(plots)} plotly figures drawn, the stored notebook has {expected}")
    locs = page.locator(".js-plotly-plot")
    for p in plots:
        k = p["index"]
        if p["traces"] == 0:
            problems.append(f"plot {k}: no traces")
        if p["no_webgl"]:
            problems.append(f"plot {k}: 'WebGL is not supported' shown")
        is3d = any(t.endswith("3d") or t in ("mesh3d", "cone", "surface") for t in p["types"])
        if is3d and not p["gl_canvas"]:
            problems.append(f"plot {k}: a 3-D figure without a WebGL canvas ({p['types']})")
        if not (p["gl_canvas"] or p["svg"]):
            problems.append(f"plot {k}: neither a WebGL canvas nor an SVG container")
        loc = locs.nth(k)
        loc.scroll_into_view_if_needed()
        page.wait_for_timeout(300)  # let WebGL paint the frame after scrolling (a redraw, not a wait for work)
        png = loc.screenshot()
        path = SCREENSHOT_DIR / f"{stem}_plot{k}.png"
        path.write_bytes(png)
        shots.append(path.name)
        p["colours"] = _distinct_colours(png)
        if p["colours"] < 8:
            problems.append(f"plot {k}: the plot area is blank ({p['colours']} colours in its centre)")
    return plots, problems


@pytest.fixture(scope="session")
def lab_results(pytestconfig, request):
    """Run the selected interactive notebooks in JupyterLab in headless Chromium; a result dict each."""
    sync_playwright = _playwright()
    selected = {item.callspec.params["info"].path.name for item in request.session.items
                if hasattr(item, "callspec") and "info" in item.callspec.params}
    notebooks = [info for info in INTERACTIVE if info.path.name in selected] or INTERACTIVE
    SCREENSHOT_DIR.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict] = {}
    t0 = time.monotonic()
    with LabServer([info.path for info in notebooks]) as server, sync_playwright() as pw:
        browser = launch_browser(pw, CHROMIUM)
        try:
            pages = {}
            for info in notebooks:
                name = info.path.name
                res = results[name] = {"console": [], "problems": [], "shots": [], "info": info}
                page = new_context(browser).new_page()  # a context per notebook: own storage
                page.on("console", lambda m, r=res: r["console"].append(_console_line(m)) if m.type == "error" else None)
                page.on("pageerror", lambda e, r=res: r["console"].append(f"uncaught: {e}"))
                page.goto(server.url(name), wait_until="domcontentloaded")
                pages[name] = page
            for name, page in pages.items():  # the tabs load in parallel; here we only wait for each
                ready = page.evaluate(LAB_JS["ready"], name)
                results[name]["kernel"] = ready
                results[name]["ready"] = time.monotonic() - t0
                if ready.get("error") or not ready.get("kernel"):
                    results[name]["problems"].append(f"notebook did not open with a kernel: {ready}")
                    continue
                page.evaluate("() => window.jupyterapp.shell.collapseLeft()")
                page.evaluate(LAB_JS["run_all"])
                results[name]["started"] = time.monotonic() - t0
            for name, page in pages.items():
                res = results[name]
                if "started" not in res:
                    continue
                left = max(5.0, RUN_TIMEOUT_S - (time.monotonic() - t0))
                try:  # run-all done, kernel idle, and every code cell executed (or one raised: the run stops)
                    page.wait_for_function(
                        """(f) => { const s = (%s)();
                                   return s.done && s.status === 'idle' && (s.executed === s.total || s.errors.length); }"""
                        % LAB_JS["state"],
                        timeout=left * 1000,
                        polling=500,
                    )
                except Exception:
                    res["problems"].append(f"Run All did not finish within {RUN_TIMEOUT_S:.0f} s "
                                           f"(state {page.evaluate(LAB_JS['state'])})")
                res["state"] = page.evaluate(LAB_JS["state"])
                res["finished"] = time.monotonic() - t0
            for name, page in pages.items():
                res = results[name]
                if "finished" not in res:
                    continue
                stem = Path(name).stem
                try:
                    page.bring_to_front()
                    res["plots"], problems = _check_plots(page, stem, res["info"].n_plotly, res["shots"])
                    res["problems"] += problems
                    res["widget_views"], res["widgets_alive"], problems = _check_widgets(page, stem, res["shots"])
                    res["problems"] += problems
                    path = SCREENSHOT_DIR / f"{stem}_page.png"
                    page.screenshot(path=str(path))
                    res["shots"].append(path.name)
                except Exception as exc:  # report it on this notebook, check the others
                    res["problems"].append(f"the browser checks stopped: {type(exc).__name__}: {exc}")
                res["checked"] = time.monotonic() - t0
        finally:
            browser.close()
        server_errors = [ln for ln in server.log_tail(100_000).splitlines() if " 500 " in ln or "Traceback" in ln]
    total = time.monotonic() - t0
    if server_errors:
        _say(pytestconfig, "JupyterLab server errors during the browser test:\n  " + "\n  ".join(server_errors[:20]))
    _say(pytestconfig, f"\nbrowser test: {len(results)} notebooks in {total:.0f} s; screenshots in {SCREENSHOT_DIR}")
    for name, res in results.items():
        _say(pytestconfig, f"  {name}: ready at {res.get('ready', float('nan')):.0f} s, finished at "
              f"{res.get('finished', float('nan')):.0f} s, checked at {res.get('checked', float('nan')):.0f} s: "
              f"{len(res.get('plots', []))} plots, {res.get('widgets_alive', 0)} widgets alive, "
              f"{len(res['console'])} console errors, {len(res['problems'])} problems")
    return results


def test_lab_extensions_installed():
    """JupyterLab draws plotly's mimetype and widgets only through these prebuilt extensions."""
    from jupyter_core.paths import jupyter_path

    wanted = {"jupyterlab-plotly": "plotly (application/vnd.plotly.v1+json)",
              "@jupyter-widgets/jupyterlab-manager": "jupyterlab_widgets (ipywidgets views)"}
    found = {name for name in wanted for d in jupyter_path("labextensions") if (Path(d) / name / "package.json").exists()}
    missing = [f"{name} from {why}" for name, why in wanted.items() if name not in found]
    assert not missing, f"JupyterLab extensions missing: {missing} (pip install -r environment.txt)"


@needs_chromium
@pytest.mark.parametrize("info", INTERACTIVE, ids=[i.path.stem for i in INTERACTIVE])
def test_notebook_renders_in_jupyterlab(lab_results, info):
    res = lab_results[info.path.name]
    print(f"screenshots of {info.path.name}: {', '.join(res['shots'])} in {SCREENSHOT_DIR}")
    problems = list(res["problems"])
    state = res.get("state") or {}
    for err in state.get("errors", []):
        problems.append(f"cell {err['cell']} raised {err['ename']}: {err['evalue']}")
    if res.get("widget_views", 0) < info.n_widgets:
        problems.append(f"{res.get('widget_views', 0)} widget views drawn, the stored notebook has {info.n_widgets}")
    if res.get("widgets_alive", 0) < info.n_sliders:
        problems.append(f"{res.get('widgets_alive', 0)} of {info.n_sliders} widgets with a slider responded to it")
    console = [m for m in res["console"] if not any(a in m for a in CONSOLE_ALLOW)]
    for m in [m for m in console if _server_hiccup(m)]:
        print(f"reported, not failed (the Jupyter server's own API under load): {m}")
    problems += [f"browser console: {m[:300]}" for m in console if not _server_hiccup(m)]
    assert not problems, f"{info.path.name} in JupyterLab:\n  " + "\n  ".join(problems)


@needs_chromium
def test_scene_html_opens_offline(tmp_path, pytestconfig):
    """``python -m course_lib sfm`` writes scene.html that draws from file:// with no network."""
    sync_playwright = _playwright()
    out = tmp_path / "sfm"
    env = {**os.environ, "COURSE_LIB_QUICK": "1"}
    proc = subprocess.run([sys.executable, "-m", "course_lib", "sfm", "--out", str(out), "--quiet"],
                          cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    html = out / "scene.html"
    assert html.exists(), f"no scene.html in {out}: {proc.stdout}"
    requests: list[str] = []
    console: list[str] = []
    with sync_playwright() as pw:
        browser = launch_browser(pw, CHROMIUM)
        try:
            page = new_context(browser, offline=True).new_page()

            def route(r):  # only the file itself may load: anything else means plotly.js is not embedded
                if r.request.url.startswith("file://"):
                    r.continue_()
                else:
                    requests.append(r.request.url)
                    r.abort()

            page.route("**/*", route)
            page.on("console", lambda m: console.append(f"{m.type}: {m.text}") if m.type == "error" else None)
            page.on("pageerror", lambda e: console.append(f"uncaught: {e}"))
            page.goto(html.as_uri())
            page.wait_for_function(
                "() => { const el = document.querySelector('.js-plotly-plot');"
                " return el && el._fullData && el._fullData.length > 0 && el.querySelector('.gl-container canvas'); }",
                timeout=60_000,
            )
            plots = page.evaluate(LAB_JS["plots"])
            fill = page.evaluate(FILL_JS)
            page.wait_for_timeout(300)
            png = page.locator(".js-plotly-plot").first.screenshot()
        finally:
            browser.close()
    SCREENSHOT_DIR.mkdir(parents=True, exist_ok=True)
    (SCREENSHOT_DIR / "sfm_scene_html.png").write_bytes(png)
    _say(pytestconfig, f"\nscene.html ({html.stat().st_size / 1e6:.1f} MB): {plots[0]['traces']} traces; screenshot "
          f"{SCREENSHOT_DIR / 'sfm_scene_html.png'}")
    assert not requests, f"scene.html asked the network for {requests[:5]}: plotly.js must be embedded"
    assert not console, "browser console: " + "; ".join(console)
    assert plots and plots[0]["traces"] > 0 and plots[0]["gl_canvas"] and not plots[0]["no_webgl"], plots
    assert _distinct_colours(png) >= 8, "scene.html: the plot area is blank"
    assert fill >= 0.25, (f"scene.html: the bulk of the points (5th..95th percentile) fills only {100 * fill:.0f} % "
                          "of the view: far-away points shrink the reconstruction to a speck")


# How much of the 3-D view the bulk of the points fills: max over axes of the 5th..95th percentile
# extent of the kit's point traces divided by the axis range shown.
FILL_JS = """() => {
    const el = document.querySelector('.js-plotly-plot');
    const pts = el._fullData.filter(t => t.meta === 'course_lib:points');
    let best = 0;
    for (const ax of ['x', 'y', 'z']) {
        const v = pts.flatMap(t => Array.from(t[ax])).filter(Number.isFinite).sort((a, b) => a - b);
        if (v.length < 2) continue;
        const q = p => v[Math.min(v.length - 1, Math.floor(p * (v.length - 1)))];
        const r = el._fullLayout.scene[ax + 'axis'].range;
        best = Math.max(best, (q(0.95) - q(0.05)) / Math.abs(r[1] - r[0]));
    }
    return best;
}"""
