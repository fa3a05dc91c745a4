"""The explorer's trade-off (issue 26) in a real headless browser: with *trade-off* ticked the
page lists the front's members with its figure, and *show* on a member draws that member
(its reversals in the status, its figures redrawn from its own answer)."""

from __future__ import annotations

import re

from test_explorer_browser import (WAIT_MS, Page, browser_context,  # noqa: F401
                                   explorer_server)


def test_the_front_is_listed_drawn_and_a_member_picked(browser_context, explorer_server):  # noqa: F811
    tab = Page(browser_context, explorer_server)
    p = tab.page
    p.fill("#n", "3")
    for i, (a, b) in enumerate(zip((50, 20, 30), (30, 40, 50)), 1):
        p.fill(f"#start-{i}", str(a))
        p.fill(f"#goal-{i}", str(b))
    p.select_option("#method", "auto")
    p.check("#pareto")
    tab.plan()
    loaded = ("kinds => kinds.every(k => { const i = document.getElementById('fig-' + k);"
              " return i && i.complete && i.naturalWidth > 0; })")
    # the front costs several plans' time (and the machine is shared): generous waits
    p.wait_for_function(loaded, arg=["pareto", "joint_angles"], timeout=WAIT_MS)
    p.wait_for_function("() => !document.getElementById('plan-button').disabled",
                        timeout=WAIT_MS)
    assert not p.is_hidden("#front-out")
    rows = p.query_selector_all("#front-rows tr")
    assert len(rows) >= 2
    assert '"pareto": true' in p.text_content("#request-preview")
    before = tab.calls_to("/v1/figures/from_plan/joint_angles")
    last = rows[-1]
    reversals = last.query_selector("td").inner_text().strip()
    last.query_selector("button").click()
    p.wait_for_function(f"() => document.getElementById('status').textContent.includes("
                        f"'{reversals} reversals')", timeout=WAIT_MS)
    p.wait_for_function(loaded, arg=["joint_angles", "chained_state"], timeout=WAIT_MS)
    assert tab.calls_to("/v1/figures/from_plan/joint_angles") == before + 1
    assert re.search(r"\d", tab.text("#ind-terminal_error"))
    # no script error (a figure or sweep answered 504 on a busy machine is the network's)
    errors = [e for e in tab.errors if not e.startswith("Failed to load resource")]
    assert not errors, errors
    tab.close()
