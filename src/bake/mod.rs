//! UV-space rasterisation and texture baking.
