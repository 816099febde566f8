"""The thermometers' contact with what they measure: a sensor lags its part and reads part of
the room air."""
from __future__ import annotations

from dataclasses import replace

from deltatwin.twin.effects.base import Effect, Parameter


class SensorContact(Effect):
    name = "sensor_contact"
    reads_temperatures = True
    summary = ("Each thermometer is a small mass glued on its part and open to the room air: "
               "it lags the part by capacity / glue and reads leak / (glue + leak) of the way "
               "from the part to the room (an air sensor follows its air within seconds). A "
               "model inverts it: part = sensor + capacity / glue * dS/dt + leak / glue * "
               "(sensor - room). Without it a sensor reads its part exactly.")
    parameters = (
        Parameter("glue_W_per_K", "W/K", 0.04, "conductance sensor - part (structure sensors)",
                  1e-9),
        Parameter("leak_W_per_K", "W/K", 0.002, "conductance sensor - room air (structure "
                  "sensors)", 0.0, fit_scale=0.001),
        Parameter("air_glue_W_per_K", "W/K", 0.2, "conductance of an air sensor to its air",
                  1e-9),
        Parameter("capacity_J_per_K", "J/K", 2.0, "heat capacity of a sensor in its clip", 1e-9),
    )

    def _contact(self, part: str) -> tuple[float, float]:
        """(glue, leak) W/K of a sensor on ``part``."""
        return ((self.air_glue_W_per_K, 0.0) if part.startswith("air")
                else (self.glue_W_per_K, self.leak_W_per_K))

    def thermometers(self, sensors):
        return tuple(replace(s, glue_W_per_K=self._contact(s.part)[0],
                             leak_W_per_K=self._contact(s.part)[1],
                             capacity_J_per_K=self.capacity_J_per_K) for s in sensors)

    def sensed_parts(self, points):
        # C dS/dt = g (P - S) + l (room - S), solved for the part temperature P
        out = {}
        for name, (part, T, rate) in points.sensor_readings.items():
            glue, leak = self._contact(part)
            out[name] = T + self.capacity_J_per_K / glue * rate + leak / glue * (T - points.room_C)
        return out
