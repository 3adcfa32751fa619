"""Example plants of the two papers: simulators and training-data collection."""
