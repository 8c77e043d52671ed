"""Readers for standard reference data sets used to validate mbcal."""
