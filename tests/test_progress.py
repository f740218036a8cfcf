"""One progress protocol: every workflow reports ``progress(done, total, message)``; the
printer and the bar take any of them."""

import jax
import jax.numpy as jnp

from jaxflex.fit import least_squares
from jaxflex.io.progress import Bar, Printer

jax.config.update("jax_enable_x64", True)

def _valley(y, k):
    return jnp.stack([k * (y[1] - y[0] ** 2), 1.0 - y[0]])


def test_the_solver_reports_each_step_of_its_cap_and_the_printer_every_kth(capsys):
    seen = []
    least_squares(jnp.asarray(10.0), jnp.array([-1.2, 1.0]), fn=_valley, max_steps=9,
                  rtol=0.0, atol=0.0, progress=lambda d, t, m: seen.append((d, t, m)))
    assert [d for d, _, _ in seen] == list(range(1, len(seen) + 1)) and len(seen) >= 3
    assert {t for _, t, _ in seen} == {9} and all("cost" in m for _, _, m in seen)
    p = Printer(every=2, prefix="> ")
    for d, t, m in seen:
        p(d, t, m)
    p(0, None, "a line without a count")
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(seen) // 2 + 1 and all(x.startswith("> ") for x in lines)
    assert lines[-1] == "> a line without a count"


def test_the_bar_follows_the_reports():
    with Bar("test", unit="step") as bar:
        bar(2, 5, "cost 1")
        assert bar._bar.n == 2 and bar._bar.total == 5
