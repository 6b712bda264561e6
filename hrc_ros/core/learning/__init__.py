"""Learning the cell's model from its recordings: bags and CSVs as per-epoch records
(`recordings`), and the input-output HMM fitted by EM with bootstrap intervals (`fit`, the
E-step kernel in `_kernels`)."""
