"""The simulated world: world files (model, schema, sense checks), the PyBullet scene, the
simulation, lenses and a run's report. The only package that imports pybullet; see docs/architecture.md."""
