"""MeasurementSet input and output: ``convert_ms`` (MS -> zarr store) and ``export_ms`` (back)."""
