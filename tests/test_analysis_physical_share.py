"""The physical share of a run's agent-time (summary.json ``presets.<name>.physical_share``)."""

from protocol.messages import AgentClass
from sumoco.analysis.summary import physical_share


def test_physical_share_over_vehicles_by_type_and_pedestrians_apart():
    car, bus, ped = int(AgentClass.PASSENGER), int(AgentClass.BUS), int(AgentClass.PEDESTRIAN)
    s = physical_share({car: [90, 100], bus: [10, 20], ped: [5, 10]})
    assert s["physical_share"] == round(100 / 120, 4)
    assert s["physical_share_by_type"] == {"passenger": 0.9, "bus": 0.5}
    assert s["physical_share_pedestrians"] == 0.5
    assert physical_share({})["physical_share"] is None
