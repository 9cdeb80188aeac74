"""Offline reports: figures and written reports people look at (matplotlib at the edge).

- ``plots``: the paper's figures and the shared headless pyplot;
- ``calib_run``: calibration fits of a campaign, in parallel over detectors;
- ``calib_report``: the calibration report (pulls, residuals, PNGs, markdown);
- ``validation_report``: the validation study's report (PNGs, markdown, JSON).
"""
