"""Stages of the chain: ingest, preprocess, world, synth (and later meshes, train, evaluate, export)."""
