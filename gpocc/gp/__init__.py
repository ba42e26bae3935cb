"""The GP occupancy model: kernels, expected kernels, local inference, training, classifier."""
