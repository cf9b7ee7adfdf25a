"""Mock flights that stand in for a firmware test: ``@pytest.mark.mock_of(NODEID, ...)`` on a test
run against the mock autopilot names the firmware test(s) that check the same on the real
firmware. Where every one of them is selected in the same session and will not be skipped
(its firmware is there), the mock's version is skipped: the real thing is the better evidence,
and the suite's critical lane is the sum of its flights. Where they are not (the fast tier,
``-m "not firmware"``, a machine without the SITL, a run of the mock's module alone), it runs."""
from __future__ import annotations

MARKER = "mock_of"


def will_run(item) -> bool:
    """False where a ``skip`` marker or a ``skipif`` marker with a true condition skips ``item`` (a
    condition given as a string is not evaluated here: taken as one that may skip)."""
    if any(True for _ in item.iter_markers("skip")):
        return False
    for m in item.iter_markers("skipif"):
        cond = m.args[0] if m.args else m.kwargs.get("condition", True)
        if isinstance(cond, str) or cond:
            return False
    return True


def stand_ins_covered(items) -> list[tuple[object, str]]:
    """(item, reason) for each selected test whose ``mock_of`` firmware tests are all selected here
    and will run."""
    selected = {i.nodeid: i for i in items}
    out = []
    for item in items:
        for m in item.iter_markers(MARKER):
            covering = [selected.get(n) for n in m.args]
            if m.args and all(c is not None and will_run(c) for c in covering):
                out.append((item, f"its firmware version runs in this session: {', '.join(m.args)}"))
                break
    return out
