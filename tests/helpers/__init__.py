"""Shared, independent reference data and computations for the tests."""
