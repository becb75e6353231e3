"""Workspace, artifacts, manifests, staleness, configs, progress and errors: the plumbing every stage shares."""
