"""The simulator engine: geometry, rendering, view synthesis. Usable as a library without the CLI."""
