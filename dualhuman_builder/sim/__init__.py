"""Ground truth and simulated devices: two-person scenes whose every vertex and contact is known,
and simulators that turn them into the noisy, drifting, clock-skewed streams a real studio
produces, in the real wire formats. Every later stage is measured against this ground truth."""
