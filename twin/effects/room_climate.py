"""The laboratory's air: air conditioning, then the room's free day/night oscillation; the
barometric pressure and humidity."""
from __future__ import annotations

import numpy as np

from deltatwin.twin.effects.base import Effect, EffectError, Parameter
from deltatwin.twin.thermal import first_order_filter


def ornstein_uhlenbeck(rng, t, std, time_s, step_s=60.0):
    """A stationary Ornstein-Uhlenbeck process (std, correlation time) sampled at times ``t``:
    generated on a coarse step and interpolated linearly."""
    coarse = np.arange(t[0], t[-1] + 2 * step_s, step_s)
    a = np.exp(-step_s / time_s)
    kicks = std * np.sqrt(1 - a * a) * rng.standard_normal(coarse.size)
    x = first_order_filter(kicks, a, std * rng.standard_normal())
    return np.interp(t, coarse, x)


class RoomClimate(Effect):
    name = "room_climate"
    summary = ("Air conditioning holds the room at its set point until it is switched off; the "
               "room then drifts to its free level with a day/night swing and a random slow "
               "wander (first-order room air); the pressure and the air's water vapour wander around "
               "their means.")
    parameters = (
        Parameter("ac_setpoint_C", "degC", 20.0, "air-conditioning set point"),
        Parameter("ac_off_s", "s", -3600.0, "time the air conditioning is switched off "
                  "(campaign time; negative = during the warm-up)"),
        Parameter("free_mean_C", "degC", 23.0, "mean room temperature without air conditioning"),
        Parameter("daily_amplitude_C", "K", 1.3, "day/night half swing", 0.0),
        Parameter("daily_peak_h", "h", 16.0, "hour of the daily maximum (campaign starts at 0 h)"),
        Parameter("wander_std_C", "K", 0.4, "std of the slow random wander", 0.0),
        Parameter("wander_time_s", "s", 6 * 3600.0, "correlation time of the wander", 1.0),
        Parameter("room_time_constant_s", "s", 2.5 * 3600.0, "room air response time", 1.0),
        Parameter("pressure_mean_Pa", "Pa", 101325.0, "mean barometric pressure", 0.0),
        Parameter("pressure_std_Pa", "Pa", 80.0, "std of the barometric wander", 0.0),
        Parameter("pressure_time_s", "s", 86400.0, "correlation time of the pressure", 1.0),
        Parameter("vapour_mean_Pa", "Pa", 1000.0, "mean water-vapour partial pressure (43 % "
                  "relative humidity at 20 degC)", 0.0),
        Parameter("vapour_std_Pa", "Pa", 0.0, "std of the water vapour's wander (a closed "
                  "laboratory's few %RH: ~50 Pa)", 0.0),
        Parameter("vapour_time_s", "s", 6 * 3600.0, "correlation time of the water vapour", 1.0),
        # what a model needs of the air by the beams, where the laboratory's air thermometers
        # sit: the twin's own beam air follows its thermal network (twin/thermal.py
        # beam_air_shares); a laboratory states these (docs/lab-setup.toml)
        Parameter("air_support_share", "1", 0.0, "share of the beams' air temperature the "
                  "interferometers' supports set: a model takes the room's temperature from "
                  "the air thermometers less it", 0.0),
        Parameter("air_table_share", "1", 0.0, "share of the beams' air temperature the "
                  "table sets (as above)", 0.0),
    )

    def __init__(self, where: str = "effect", check_minimum: bool = True, **values):
        super().__init__(where, check_minimum, **values)
        if min(self.air_support_share, self.air_table_share) < 0:
            raise EffectError(f"{where}: air_support_share = {self.air_support_share:g}, "
                              f"air_table_share = {self.air_table_share:g}: shares of the "
                              "beams' air temperature are not negative")
        if self.air_support_share + self.air_table_share >= 0.9:
            raise EffectError(f"{where}: air_support_share + air_table_share = "
                              f"{self.air_support_share + self.air_table_share:g}: the beams' "
                              "air must follow the room mostly (the shares sum below 0.9)")

    def environment(self, env, rng):
        t = env.t_grid
        free = (self.free_mean_C
                + self.daily_amplitude_C * np.cos(2 * np.pi * (t / 3600.0 - self.daily_peak_h) / 24.0)
                + ornstein_uhlenbeck(rng, t, self.wander_std_C, self.wander_time_s))
        target = np.where(t < self.ac_off_s, self.ac_setpoint_C, free)
        a = np.exp(-(t[1] - t[0]) / self.room_time_constant_s)
        env.room_C = first_order_filter((1 - a) * target, a, target[0])
        env.pressure_Pa = self.pressure_mean_Pa + ornstein_uhlenbeck(
            rng, t, self.pressure_std_Pa, self.pressure_time_s)
        # the vapour's draws come from a child of the stream (spawning does not advance it):
        # the effects drawing after this one keep the draws they had before it was added
        env.vapour_Pa = self.vapour_mean_Pa + (ornstein_uhlenbeck(
            rng.spawn(1)[0], t, self.vapour_std_Pa, self.vapour_time_s)
            if self.vapour_std_Pa > 0 else np.zeros(t.size))
