"""hil_sim: the simulated impact-test rig that stands in for every device."""
