"""The live view of a run with ``estimation`` in a real browser (headless Chromium): ``dmpc watch`` on a
run folder of scenarios/fourtank-levels.yaml draws, per subsystem, the state estimates x^ beside
the states, the levels measured and the disturbance estimates of ``trajectory.npz``, and its
readout has them at the chosen step.

Chromium and its driver come from Debian, as for test_watch_browser.py: without them the test is
skipped, except in CI, where it fails. With ``DMPC_WATCH_SCREENSHOTS=DIR`` it saves what the
browser showed as DIR/watch-estimates.png (docs/figures/watch-estimates.png was made so).
"""
from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.browser import chromium, class_text, model, require_chromium, wait_until
from tests.test_watch_browser import replaying, screenshot

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

STEPS = 120


def test_replay_of_a_run_with_estimation_draws_its_estimates(tmp_path):
    require_chromium()
    import dmpc

    folder = tmp_path / "levels"
    dmpc.simulate("scenarios/fourtank-levels.yaml", out=folder, steps=STEPS)
    npz = np.load(folder / "trajectory.npz")
    with chromium(height=1500) as driver:
        with replaying(driver, folder, STEPS):
            for i, name in enumerate(("a", "b")):
                data = model(driver, f"estimates-{name}",
                             "['k', 'xhat1', 'xhat2', 'y1', 'd1'].map(c => Array.from(m.data[c]))")
                assert data[0] == list(range(STEPS))
                np.testing.assert_array_equal(np.column_stack(data[1:3]), npz["x_hat"][:, 2 * i:2 * i + 2])
                np.testing.assert_array_equal(data[3], npz["y"][:, i])
                np.testing.assert_array_equal(data[4], npz["d_hat"][:, i])
                for glyph in (f"estimate-{name}-1", f"estimate-{name}-2", f"measured-{name}-1"):
                    assert model(driver, glyph, "m.visible") is True, glyph
                assert model(driver, f"disturbances-{name}", "m.title.text") == f"subsystem {name}: disturbances d̂(k)"
            k = 30
            driver.execute_script(f"Bokeh.documents[0].get_model_by_name('step-slider').value = {k}")
            expected = ", ".join(f"{v:.6g}" for v in npz["x_hat"][k, :2])
            wait_until(lambda: class_text(driver, "dmpc-x-hat") == expected, 10, what="x^ in the readout")
            assert class_text(driver, "dmpc-d-hat") == f"{npz['d_hat'][k, 0]:.6g}"
            assert class_text(driver, "dmpc-y") == f"{npz['y'][k, 0]:.6g}"
            screenshot(driver, "watch-estimates.png")
