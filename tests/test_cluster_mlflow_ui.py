"""System test, the MLflow UI: the runs of the jobs submitted to the real local Ray cluster (the session's
`jobs` and `cluster` fixtures, tests/conftest.py and tests/cluster_helpers.py) looked at in headless
Chromium driven by Selenium WebDriver (the `browser` fixture, Debian's chromium-driver): the runs list;
then the compare view of the sweep's trials, clicked and typed through as a user would, with the
screenshot kept as docs/mlflow_ui.png when ANIFORMER_KEEP_SCREENSHOT names it. And the server's backup on
stop. Each test sets up what it needs through fixtures, so any one runs alone or in any order.
"""

from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import time
from pathlib import Path

import pytest
from cluster_helpers import TRIALS, healthy, mlflow_runs, running, start, stop, tags, tree_pids, wait_for
from selenium.common.exceptions import (
    ElementClickInterceptedException,
    ElementNotInteractableException,
    NoSuchElementException,
    StaleElementReferenceException,
    WebDriverException,
)
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys
from selenium.webdriver.support import expected_conditions as EC
from selenium.webdriver.support.ui import WebDriverWait

pytestmark = pytest.mark.slow

# the `browser` fixture (tests/conftest.py): Selenium WebDriver over Debian's chromium and chromium-driver
NEEDS_BROWSER = pytest.mark.skipif(
    not (shutil.which("chromium") or shutil.which("chromium-browser")) or not shutil.which("chromedriver"),
    reason="no chromium or chromedriver (.ci/run installs Debian's chromium and chromium-driver)")


@NEEDS_BROWSER
def test_mlflow_ui_in_a_real_browser_shows_the_runs(cluster, jobs, browser, tmp_path):
    experiment, runs = mlflow_runs(cluster)
    names = {r["info"]["run_name"] for r in runs}
    assert {"tiny", "sweep"} <= names
    shot = tmp_path / "mlflow_ui.png"
    driver = browser(1600, 900)
    driver.get(f"{cluster.mlflow}/#/experiments/{experiment}/runs")
    # the UI is a React app: it fetches the runs, then draws them (slowly on a loaded machine)
    for name in ("tiny", "sweep"):
        WebDriverWait(driver, 120).until(EC.visibility_of_element_located((By.XPATH, f"//*[text()={_literal(name)}]")),
                                         f"the run {name} in the runs list")
    dom = driver.page_source
    assert ">tiny<" in dom and ">sweep<" in dom, dom[-3000:]
    assert "matching runs" in dom or "Run Name" in dom
    driver.save_screenshot(shot)
    image = _png_stats(shot)
    assert image["width"] >= 1200 and image["height"] >= 800
    assert image["colours"] > 200 and 0.05 < image["ink"] < 0.95, image  # a rendered page, not a blank one


# ------------------------------------------------------------------ the compare view, clicked through with Selenium

SWEPT = ["loss.rec", "loss.motion", "loss.appearance", "data.window"]  # the sweep's searched params (tune.PARAMS)
# what a click or a wait may meet while the UI re-renders: the wait tries again
FLAKY = (StaleElementReferenceException, ElementClickInterceptedException, ElementNotInteractableException,
         NoSuchElementException)


def _literal(text: str) -> str:
    """`text` as an XPath string literal."""
    assert '"' not in text, text
    return f'"{text}"'


def _has_class(name: str) -> str:
    """An XPath predicate: the element has the class `name`."""
    return f"contains(concat(' ', normalize-space(@class), ' '), ' {name} ')"


def _shown(driver, xpath: str) -> list:
    """The displayed elements that `xpath` finds."""
    return [e for e in driver.find_elements(By.XPATH, xpath) if e.is_displayed()]


def _click(driver, xpath: str, what: str, timeout: float = 60) -> None:
    """Click, as a user does, the first displayed element `xpath` finds, once there is one: scroll it into
    view with the wheel, move the mouse to its middle and press there. (Not `WebElement.click()`: that
    refuses when the element at that point is another, as under a select's arrow, which lets clicks
    through to the select.)"""

    def clicked(d) -> bool:
        shown = _shown(d, xpath)
        if shown:
            ActionChains(d).scroll_to_element(shown[0]).move_to_element(shown[0]).click().perform()
        return bool(shown)

    WebDriverWait(driver, timeout, ignored_exceptions=FLAKY).until(clicked, f"{what} to click")


def _keys(driver, *keys: str, hold: str | None = None) -> None:
    """Type `keys` into whatever has the focus (the keyboard), holding `hold` (a modifier) down."""
    actions = ActionChains(driver)
    if hold:
        actions.key_down(hold)
    actions.send_keys(*keys)
    if hold:
        actions.key_up(hold)
    actions.perform()


def _text(driver) -> str:
    return driver.execute_script("return document.body ? document.body.innerText : ''")


def _choose(driver, field: str, keys: list[str]) -> list[str]:
    """Pick `keys` in the multiple-choice select after the label `field` ("Parameters:", "Metrics:") of the
    parallel-coordinates controls: open it (its arrow, away from the chosen tags and their remove buttons),
    type the key, click the option that matches it exactly."""
    select = f"//div[.={_literal(field)}]/following-sibling::*[1]"
    options = f"//*[{_has_class('du-bois-light-select-item-option')}]"

    def box(d):
        return d.find_element(By.XPATH, f"{select}//input")

    def chosen(d) -> list[str]:
        return [e.get_property("textContent") for e in
                d.find_elements(By.XPATH, f"{select}//*[{_has_class('du-bois-light-select-selection-item-content')}]")]

    def wait(condition, what: str):
        return WebDriverWait(driver, 10, ignored_exceptions=FLAKY).until(condition, what)

    for key in keys:
        for attempt in range(3):  # a click or keys landing while the UI re-renders: try again
            try:
                wait(lambda d: not _shown(d, options), "no dropdown open")
                _click(driver, f"{select}//*[{_has_class('du-bois-light-select-arrow')}]", f"the {field} arrow", timeout=10)
                wait(lambda d: d.switch_to.active_element == box(d), f"focus on the {field} box")
                if box(driver).get_property("value"):  # what was typed for the last one may still be there
                    _keys(driver, "a", hold=Keys.CONTROL)
                    _keys(driver, Keys.BACKSPACE)
                    wait(lambda d: box(d).get_property("value") == "", f"an empty {field} box")
                _keys(driver, key)
                _click(driver, f"{options}[.={_literal(key)}]", f"option {key}", timeout=10)
                wait(lambda d, key=key: key in chosen(d), f"{key} chosen")
                break
            except WebDriverException as e:
                if attempt == 2:
                    state = [box(driver).get_property("value"), chosen(driver),
                             [o.get_property("textContent") for o in _shown(driver, options)][:10]]
                    raise AssertionError(f"{field} {key}: {e.msg} (typed, chosen, options shown: {state})") from None
            finally:
                _keys(driver, Keys.ESCAPE)
    return chosen(driver)


def _pick(driver, select_id: str, key: str) -> None:
    """Choose `key` in the single-choice select (a button that opens a list of options) `select_id`."""
    button = f"//*[@id={_literal(select_id)}]"
    listed = "//*[@role='option']"
    for attempt in range(3):
        try:
            WebDriverWait(driver, 10, ignored_exceptions=FLAKY).until(lambda d: not _shown(d, listed), "no list open")
            _click(driver, button, select_id, timeout=10)
            _click(driver, f"{listed}[.={_literal(key)}]", f"option {key}", timeout=10)
            WebDriverWait(driver, 10, ignored_exceptions=FLAKY).until(
                lambda d: d.find_element(By.XPATH, button).get_property("textContent") == key, f"{key} in {select_id}")
            return
        except WebDriverException as e:
            if attempt == 2:
                shown = [driver.find_element(By.XPATH, button).get_property("textContent"),
                         [o.get_property("textContent") for o in _shown(driver, listed)][:10]]
                raise AssertionError(f"{select_id} {key}: {e.msg} (shown, options: {shown})") from None
            if _shown(driver, listed):
                _keys(driver, Keys.ESCAPE)


def _compare_view(driver, url: str, names: list[str], shot: Path) -> dict:
    """Open the compare view of a sweep's trials; plot the swept params and pmd_unseen in parallel
    coordinates (screenshot with the params that differ), then each swept param against pmd_unseen
    in the scatter plot. What the page showed."""
    import io

    from PIL import Image  # matplotlib's dependency

    seen = {}
    driver.get(url)
    WebDriverWait(driver, 60).until(lambda d: all(s in _text(d) for s in ["Parallel Coordinates Plot", *names]),
                                    "the compare view of the trials")
    close = "//*[@data-component-id='mlflow.assistant.chat_panel.close']"
    if _shown(driver, close):  # MLflow 3's assistant panel takes a third of the width
        _click(driver, close, "the assistant's close button")
    _click(driver, "//button[.='Clear All']", "Clear All")
    seen["params"] = _choose(driver, "Parameters:", SWEPT)
    seen["metrics"] = _choose(driver, "Metrics:", ["pmd_unseen"])
    plot = "document.querySelector('[id$=content-parallel-coordinates-plot] .js-plotly-plot')"
    WebDriverWait(driver, 60).until(
        lambda d: d.execute_script(f"const p = {plot}; return !!(p && p.data && p.data[0].dimensions.length === 5)"),
        f"the 5 axes (chosen: {seen['params']}, {seen['metrics']})")
    seen["axes"] = driver.execute_script(f"return {plot}.data[0].dimensions.map(d => [d.label, d.values])")
    seen["axis_titles"] = [e.get_property("textContent")
                           for e in driver.find_elements(By.CSS_SELECTOR, ".parcoords .axis-title")]
    diff = "//button[@aria-label='Parameters - Show diff only']"
    _click(driver, diff, "Parameters: show diff only")
    WebDriverWait(driver, 60, ignored_exceptions=FLAKY).until(
        lambda d: d.find_element(By.XPATH, diff).get_attribute("aria-checked") == "true", "only the params that differ")
    driver.execute_script("[...document.querySelectorAll('*')].forEach(e => { if (e.scrollTop) e.scrollTop = 0; })")
    table = driver.find_element(By.XPATH, f"{diff}/ancestor::*[{_has_class('du-bois-light-collapse-content-box')}][1]//table")
    bottom = table.rect["y"] + table.rect["height"]
    seen["text"] = _text(driver)
    with Image.open(io.BytesIO(driver.get_screenshot_as_png())) as page:  # from the top to the end of those params
        page.crop((0, 0, page.width, min(page.height, int(bottom) + 24))).save(shot)
    _click(driver, "//*[@role='tab'][.='Scatter Plot']", "the Scatter Plot tab")
    scatter = "document.querySelector('[id$=content-scatter-plot] .js-plotly-plot')"
    seen["scatter"] = {}
    for param in SWEPT:
        for axis, key in (("x", param), ("y", "pmd_unseen")):
            _pick(driver, f"{axis}-axis-selector", key)
        seen["scatter"][param] = driver.execute_script(
            f"const t = {scatter}.data[0]; "
            "return {x: t.x, y: t.y, names: t.text.map(s => s.split('</b>')[0].replace('<b>', ''))};")
    return seen


@NEEDS_BROWSER
def test_mlflow_compare_view_shows_the_sweeps_trials_in_a_real_browser(cluster, jobs, browser, tmp_path):
    """The compare view of the sweep's children (the link `pipeline.sweep_table.compare_link` prints), as a user
    reaches it: parallel coordinates over lambda_rec, lambda_m, lambda_a, T and pmd_unseen, the scatter of
    each against pmd_unseen; the values drawn are the runs' own. Screenshot: ANIFORMER_KEEP_SCREENSHOT
    (docs/mlflow_ui.png)."""
    from pipeline.sweep_table import compare_url

    experiment, runs = mlflow_runs(cluster)
    (parent,) = [r for r in runs if r["info"]["run_name"] == "sweep"]
    children = sorted((r for r in runs if tags(r).get("mlflow.parentRunId") == parent["info"]["run_id"]),
                      key=lambda r: r["info"]["run_name"])
    assert len(children) == TRIALS, "the sweep job did not run"
    params = [{p["key"]: p["value"] for p in r["data"]["params"]} for r in children]
    pmd = [{m["key"]: m["value"] for m in r["data"]["metrics"]}["pmd_unseen"] for r in children]
    names = [r["info"]["run_name"] for r in children]
    url = compare_url(cluster.mlflow, experiment, [r["info"]["run_id"] for r in children])
    shot = tmp_path / "mlflow_compare.png"
    started = time.time()
    # Tall enough that nothing scrolls (the page scrolls inside its own panel; resizing later can
    # re-mount the plot's controls, losing what was chosen): the screenshot is the top of it.
    seen = _compare_view(browser(1600, 3000), url, names, shot)
    print(f"compare view driven in {time.time() - started:.1f} s")

    assert seen["params"] == SWEPT and seen["metrics"] == ["pmd_unseen"], seen
    assert seen["axis_titles"] == [*SWEPT, "pmd_unseen"], seen["axis_titles"]
    # the lines are the trials: each axis holds the runs' values (the UI's run order is the URL's)
    axes = dict((label, values) for label, values in seen["axes"])
    for key in SWEPT:
        assert sorted(axes[key]) == pytest.approx(sorted(float(p[key]) for p in params)), key
    assert sorted(axes["pmd_unseen"]) == pytest.approx(sorted(pmd))
    text = seen["text"]
    assert all(name in text for name in names) and "Show diff only" in text
    for p in params:  # the diff-only table: the swept values of every trial
        assert p["loss.rec"] in text and p["loss.appearance"] in text, p
    for key in SWEPT:  # each swept value against pmd_unseen, one point per trial, named
        points = seen["scatter"][key]
        by_name = {n: (float(x), y) for n, x, y in zip(points["names"], points["x"], points["y"])}
        assert by_name == {n: (pytest.approx(float(p[key])), pytest.approx(v)) for n, p, v in zip(names, params, pmd)}
    image = _png_stats(shot)
    assert image["width"] == 1600 and image["height"] >= 900, image
    assert image["colours"] > 200 and 0.05 < image["ink"] < 0.95, image
    keep = os.environ.get("ANIFORMER_KEEP_SCREENSHOT")
    if keep:
        shutil.copyfile(shot, keep)


def _png_stats(path: Path) -> dict:
    import numpy as np
    from PIL import Image  # matplotlib's dependency

    with Image.open(path) as im:
        rgb = np.asarray(im.convert("RGB"))
    packed = (rgb[..., 0].astype(np.int64) << 16) | (rgb[..., 1].astype(np.int64) << 8) | rgb[..., 2]
    return {"width": rgb.shape[1], "height": rgb.shape[0], "colours": len(np.unique(packed)),
            "ink": float((rgb.min(axis=-1) < 240).mean())}  # share of pixels that are not (near) white


def test_stopping_the_mlflow_server_leaves_a_backup_with_the_runs(cluster, jobs):
    """Stopped, the server backs its store up; it is then started again on the same store, as the
    cluster's head would restart it, so that the tests after this one find it (any order)."""
    server = cluster.procs["mlflow"]
    started = tree_pids(server.pid)
    os.kill(server.pid, signal.SIGTERM)  # the wrapper: stops its server, then backs the store up
    try:
        server.wait(timeout=120)
        assert server.returncode == 0, cluster.tail("mlflow")
        assert not [pid for pid in started if running(pid)], "the MLflow server left processes behind"
        with sqlite3.connect(cluster.root / "mlflow-backup" / "mlflow.db") as db:
            names = {name for (name,) in db.execute("select name from runs")}
        assert {"tiny", "sweep"} <= names
    finally:
        stop([server], grace=30)
        start(cluster, "mlflow", cluster.commands["mlflow"])
        wait_for("the MLflow server, started again", lambda: healthy(cluster.mlflow), cluster)
    _, runs = mlflow_runs(cluster)  # the same store, served again
    assert {"tiny", "sweep"} <= {r["info"]["run_name"] for r in runs}
