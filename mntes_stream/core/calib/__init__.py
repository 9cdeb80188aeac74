"""Ground calibration (paper section 4): measurements, simulation, per-detector fits."""
