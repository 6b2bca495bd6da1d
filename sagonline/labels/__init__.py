"""The labels per Gaussian, taken with you: labels.npy / labels.json, object PLYs, renders."""
