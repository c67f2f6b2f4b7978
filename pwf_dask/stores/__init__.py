"""Stores on disk: the scan and reconstruction layouts (scan_io), chunk integrity (integrity), detector
files in (ingest) and TIFF out (export). The only modules that read or write Zarr besides the pipeline.
"""
