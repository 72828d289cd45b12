"""Plays a scene's timeline of input events into a Simulator at their times.

The same events become ROS messages in launch_scripts/run_scene (the publisher
process); here they are applied in-process for headless runs and replay checks.
"""


class TimelinePlayer:
    """events: the scene's timeline (list of dicts with t and topic), applied in time order."""

    def __init__(self, events):
        self.events = sorted(events, key=lambda e: e["t"])
        self.next = 0

    def apply_due(self, sim):
        """Apply every event with t <= sim.time (+ half a step, so t = k dt lands on step k)."""
        applied = []
        while self.next < len(self.events) and self.events[self.next]["t"] <= sim.time + 0.5 * sim.dt:
            ev = self.events[self.next]
            apply_event(sim, ev)
            applied.append(ev)
            self.next += 1
        return applied


def apply_event(sim, ev):
    topic = ev["topic"]
    if topic == "wrench":
        sim.set_wrench(ev["frame_id"], force=ev.get("force", (0, 0, 0)), torque=ev.get("torque", (0, 0, 0)))
    elif topic == "point_force":
        sim.add_point_force(ev["point"], ev["force"], ev.get("duration", 0.0))
    elif topic == "collider_pose":
        sim.set_collider_pose(ev["name"], ev["position"], ev.get("orientation", (0, 0, 0, 1)))
    elif topic == "clear_forces":
        sim.clear_forces()
    else:
        raise ValueError(f"unknown timeline topic {topic!r}")
