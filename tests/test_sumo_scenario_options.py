"""The scenario is the truth (real libsumo): its step length, seed and begin stand unless the
run sets them; durations count from the begin; a scenario that ends first ends the run;
SUMO's own outputs go to the run's folder; a SUMO error mid-run is one line."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from sumo_side.config import SumoConfig
from sumo_side.simulation import SumoFailed, SumoSim, scenario_options
from tests.sumo_testnet import make_testnet

BAD_ROUTES = """<routes>
  <vType id="car" vClass="passenger"/>
  <vehicle id="ok" type="car" depart="0"><route edges="A0B0 B0B1"/></vehicle>
  <vehicle id="filler" type="car" depart="4"><route edges="A0B0 B0B1"/></vehicle>
  <vehicle id="bad" type="car" depart="5"><route edges="A0B0 NOPE"/></vehicle>
</routes>
"""


@pytest.fixture(scope="module")
def net(tmp_path_factory) -> Path:
    return make_testnet(tmp_path_factory.mktemp("opts"))


def _variant(cfg: Path, name: str, time: str = "", output: str = "", routes: str = "routes.rou.xml") -> Path:
    """The test scenario with other <time>/<output> options, next to the original."""
    text = cfg.read_text().replace('<route-files value="routes.rou.xml"/>', f'<route-files value="{routes}"/>')
    text = text.replace('<time>\n    <begin value="0"/>\n    <step-length value="0.1"/>\n  </time>',
                        f"<time>{time}</time>")
    text = text.replace("</configuration>", f"<output>{output}</output>\n</configuration>")
    p = cfg.parent / name
    p.write_text(text)
    return p


def _started(cfg: Path, **kw) -> SumoSim:
    sim = SumoSim(SumoConfig(sumocfg=cfg, **{k: v for k, v in kw.items() if k in ("step_length_s", "begin_s",
                                                                                   "extra_args")}),
                  seed=kw.get("seed"), output_dir=kw.get("output_dir"))
    sim.start()
    return sim


def test_reading_the_options_of_a_sumocfg(net):
    cfg = _variant(net, "opts.sumocfg", '<begin value="13:58:20"/><end value="50400"/><step-length value="0.5"/>'
                   '<seed value="17"/>')
    o = scenario_options(cfg)
    assert (o.step_length_s, o.begin_s, o.end_s, o.seed) == (0.5, 50300.0, 50400.0, 17)
    silent = scenario_options(_variant(net, "silent.sumocfg"))
    assert (silent.step_length_s, silent.begin_s, silent.end_s, silent.seed) == (1.0, 0.0, None, None)


def test_the_scenario_step_length_and_seed_stand(net, caplog):
    cfg = _variant(net, "half.sumocfg", '<step-length value="0.5"/><seed value="17"/>')
    caplog.set_level(logging.INFO, logger="sumo_side.simulation")
    sim = _started(cfg)
    try:
        assert sim.step_length == 0.5 == sim.api.simulation.getDeltaT()
        assert sim.api.simulation.getOption("seed") == "17"
        sim.step()
        assert sim.read().time == pytest.approx(0.5)
    finally:
        sim.close()
    assert "step length 0.5 s (the scenario's)" in caplog.text
    assert "seed 17 (the scenario's)" in caplog.text


def test_the_run_overrides_only_when_it_says_so_and_logs_both(net, caplog):
    cfg = _variant(net, "half2.sumocfg", '<step-length value="0.5"/><seed value="17"/>')
    caplog.set_level(logging.INFO, logger="sumo_side.simulation")
    sim = _started(cfg, step_length_s=0.2, seed=5)
    try:
        assert sim.step_length == 0.2 == sim.api.simulation.getDeltaT()
        assert sim.api.simulation.getOption("seed") == "5"
    finally:
        sim.close()
    assert "step length 0.2 s: [sumo] step_length_s replaces the scenario's 0.5 s" in caplog.text
    assert "seed 5: the run's seed replaces the scenario's 17" in caplog.text


def test_duration_counts_from_the_begin_and_an_earlier_end_wins(net):
    cfg = _variant(net, "late.sumocfg", '<begin value="5"/><end value="7"/><step-length value="0.1"/>')
    sim = _started(cfg)
    try:
        assert sim.begin_time == 5.0
        reasons = []
        for _ in range(20):
            sim.step()
            sim.read()
            reasons.append(sim.finished(1.0))
        # a 1 s duration ends after 10 steps although SUMO's clock is at 6 s ...
        assert reasons[8] == "" and reasons[9] == "duration 1 s reached"
        # ... and a scenario that ends (7 s) before the duration (5 s from 5 s) ends the run
        assert sim.finished(5.0) == "the scenario's end time 7 s reached"
    finally:
        sim.close()


def test_begin_moves_the_start(net):
    sim = _started(net, begin_s=7.0)
    try:
        assert sim.begin_time == 7.0
        sim.step()
        assert sim.read().time == pytest.approx(7.1)
    finally:
        sim.close()


def test_sumo_outputs_land_in_the_output_folder(net, tmp_path):
    cfg = _variant(net, "outputs.sumocfg", '<step-length value="0.1"/>',
                   output='<tripinfo-output value="trips.xml"/><summary-output value="summary.xml"/>')
    sim = _started(cfg, output_dir=tmp_path / "run" / "sumo")
    try:
        for _ in range(5):
            sim.step()
    finally:
        sim.close()
    assert (tmp_path / "run" / "sumo" / "trips.xml").is_file()
    assert (tmp_path / "run" / "sumo" / "summary.xml").is_file()
    assert not (net.parent / "trips.xml").exists()


def test_a_sumo_error_mid_run_is_one_line(net):
    (net.parent / "bad.rou.xml").write_text(BAD_ROUTES)
    cfg = _variant(net, "bad.sumocfg", '<step-length value="0.1"/><route-steps value="1"/>', routes="bad.rou.xml")
    sim = _started(cfg)
    try:
        with pytest.raises(SumoFailed) as err:
            for _ in range(100):
                sim.step()
                sim.read()
    finally:
        sim.close()
    text = str(err.value)
    assert "\n" not in text and "NOPE" in text and "SUMO failed" in text
