"""Settings check themselves: a configuration class refuses a value outside its range by
name, and every command's ``--segment`` takes samples or seconds alike."""

import argparse

import pytest

from jaxflex.app.cli.spans import Span, span, span_or_auto
from jaxflex.discover import DiscoverConfig
from jaxflex.io.errors import ConfigError, InputError


@pytest.mark.parametrize("setting, value", [
    ("train_frac", 0.95), ("segment", 0.0), ("substeps", 2.5), ("substeps", 17),
    ("max_effects", -1), ("alpha", 0.0), ("model", "stiff"), ("max_order", 0)])
def test_discover_config_refuses_a_setting_by_name(setting, value):
    with pytest.raises(ConfigError) as e:
        DiscoverConfig(**{setting: value})
    assert e.value.field == setting and isinstance(e.value, InputError)
    assert e.value.option().startswith("--" + setting.replace("_", "-"))


def test_a_default_discover_config_is_valid():
    assert DiscoverConfig().segment == 0.3


def test_a_span_is_samples_or_seconds():
    assert span("250") == Span(250, "samples") and span("0.25s") == Span(0.25, "s")
    assert span("250").seconds(1e-3) == pytest.approx(0.25)
    assert span("0.25s").samples(1e-3) == 250 and span("0.25s").samples(4e-3) == 62
    assert span_or_auto("auto") == "auto" and span("0").samples(1e-3) == 0
    for bad in ("-1", "x", "1.5", "-0.2s", "infs", "nans"):
        with pytest.raises(argparse.ArgumentTypeError, match="samples .* or seconds"):
            span(bad)
