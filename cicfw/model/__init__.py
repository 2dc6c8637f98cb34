"""The model: a shared encoder, a branch mixer and an output head, composed by CICModule."""
