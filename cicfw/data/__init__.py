"""Data: the CIL HDF5 format, the datamodule, augmentation and the command-balanced sampler."""
