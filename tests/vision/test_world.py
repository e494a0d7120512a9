"""The static world a rasterizer draws, read from a SUMO network (vision/world.py)."""


def test_lane_change_rules_are_read_per_lane(tmp_path):
    from crchfl_sumo.vision.world import _read_lane_change_rules

    net = tmp_path / "rules.net.xml"
    net.write_text(
        '<net><edge id="e"><lane id="e_0" changeLeft="bus" shape="0,0 10,0"/>'
        '<lane id="e_1" changeRight="passenger taxi" changeLeft="all" shape="0,3 10,3"/>'
        '<lane id="e_2" shape="0,6 10,6"><param key="k" value="v"/></lane></edge></net>'
    )
    assert _read_lane_change_rules(net) == {"e_0": (False, True), "e_1": (True, True), "e_2": (True, True)}
