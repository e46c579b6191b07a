"""The simulated robot's true build, kept when its config is rewritten (``mazebot calibrate --sim --write``).

``[sim]`` describes the true robot relative to the other sections (true wheel diameter
over the configured one, swapped channels, a reversed encoder). When calibration
corrects those sections the physical robot does not change, so its ``[sim]`` keys are
expressed again relative to the new values: the same true wheels, track, lidar mount and
wiring, now (nearly) matching the config.
"""

from __future__ import annotations

from mazebot.config import Config


def _configured_diameters_m(config: Config) -> tuple[float, float]:
    d, ratio = config.drive.wheel_diameter_m, config.drive.wheel_diameter_ratio
    return d * 2.0 / (1.0 + ratio), d * 2.0 * ratio / (1.0 + ratio)


def same_true_robot(old: Config, new: Config) -> Config:
    """``new`` with ``[sim]`` describing the true robot ``old`` described (module docstring)."""
    out = new.model_copy(deep=True)
    s_old, s = old.sim, out.sim
    old_left_m, old_right_m = _configured_diameters_m(old)
    new_left_m, new_right_m = _configured_diameters_m(new)
    s.wheel_diameter_left_scale = old_left_m * s_old.wheel_diameter_left_scale / new_left_m
    s.wheel_diameter_right_scale = old_right_m * s_old.wheel_diameter_right_scale / new_right_m
    s.track_width_scale = old.drive.track_width_m * s_old.track_width_scale / new.drive.track_width_m
    s.lidar_mount_yaw_error_deg = old.lidar.mount_yaw_deg + s_old.lidar_mount_yaw_error_deg - new.lidar.mount_yaw_deg
    # motors: the channel each wheel is truly on, and its true polarity
    m_old, m = old.motors, new.motors
    true_channel = {"left": m_old.left_channel, "right": m_old.right_channel}
    if s_old.motor_channels_swapped:
        true_channel = {"left": m_old.right_channel, "right": m_old.left_channel}
    s.motor_channels_swapped = true_channel["left"] != m.left_channel
    s.left_motor_reversed = (m_old.left_invert != s_old.left_motor_reversed) != m.left_invert
    s.right_motor_reversed = (m_old.right_invert != s_old.right_motor_reversed) != m.right_invert
    # encoders: the pins each wheel's encoder is truly on, and its true count direction
    e_old, e = old.encoders, new.encoders
    true_left_pin = e_old.right_a_pin if s_old.encoder_pins_swapped else e_old.left_a_pin
    s.encoder_pins_swapped = true_left_pin != e.left_a_pin
    s.left_encoder_reversed = (e_old.left_invert != s_old.left_encoder_reversed) != e.left_invert
    s.right_encoder_reversed = (e_old.right_invert != s_old.right_encoder_reversed) != e.right_invert
    return out
