//! Sphere tracing, differentiable surface points, stage-1 and stage-2 renderers.
