"""Example plants of the two papers: simulators and training-data collection.

* `gpmhe.systems.batch_reactor`: the batch reactor 2A -> B of the GP-MHE paper (model, simulator,
  the offline training trajectories and the paper's MHE settings);
* `gpmhe.systems.second_order`: the second-order plant with a hidden disturbance z(ζ) of the
  RGP-dKF paper (scenarios S1–S3, the RGP-dKF and the RGP-B baseline).

See the user guide, *Example systems*.
"""
