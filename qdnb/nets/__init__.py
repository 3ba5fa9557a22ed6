"""Neural networks: the policy and critic MLPs, and the causal transformer blocks
(with their key/value cache) that the QDT and the FLT share."""
