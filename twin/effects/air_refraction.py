"""The air's refractive index along each beam and the interferometer's own compensation."""
from __future__ import annotations

from deltatwin.twin.effects.base import Effect, Parameter
from deltatwin.twin.instruments.optics import air_index


class AirRefraction(Effect):
    name = "air_refraction"
    reads_temperatures = True
    summary = ("The beam's air index (Edlén/Birch-Downs) follows its air temperature, the "
               "barometric pressure and humidity; the instrument divides by an index computed "
               "from its own air sensor and a fixed pressure and humidity, so sensor lag and "
               "offset, the air the sensor does not see, and pressure and humidity changes times "
               "the dead path remain. A model takes the air's pressure and humidity from the "
               "laboratory's barometer and hygrometer (p_Pa, RH_pct) when the data have them.")
    parameters = (
        Parameter("wavelength_m", "m", 632.99e-9, "HeNe vacuum wavelength", 0.0),
        Parameter("beam_room_fraction", "-", 0.3,
                  "fraction of the beam path in room air rather than the air by the sensor", 0.0,
                  fit_scale=0.2),
        Parameter("compensation_offset_C", "degC", (0.02, -0.03, 0.01),
                  "error of each axis' compensation air sensor", fit_scale=0.05, fit_start=0.0),
        Parameter("assumed_pressure_Pa", "Pa", 101325.0, "pressure the instrument assumes", 0.0),
        Parameter("vapour_pressure_Pa", "Pa", 1000.0, "water-vapour partial pressure the "
                  "instrument assumes (and a model's air's, without a humidity record)", 0.0),
    )

    def optics(self, points, optics):
        vapour = self.vapour_pressure_Pa if points.vapour_Pa is None else points.vapour_Pa
        for k, axis in enumerate(("x", "y", "z")):
            T_air = points.node_T[f"air_{axis}"]
            T_beam = (1.0 - self.beam_room_fraction) * T_air + self.beam_room_fraction * points.room_C
            optics.n_air[axis] = air_index(T_beam, points.pressure_Pa, vapour, self.wavelength_m)
            T_sensor = points.node_T[f"sensor:comp_{axis}"] + self.compensation_offset_C[k]
            optics.n_comp[axis] = air_index(T_sensor, self.assumed_pressure_Pa,
                                            self.vapour_pressure_Pa, self.wavelength_m)
