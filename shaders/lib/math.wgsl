// Shared math helpers.
const PI: f32 = 3.14159265358979323846;
const INV_PI: f32 = 0.31830988618379067154;

// Numerically safe softplus with sharpness beta: log(1 + exp(beta x)) / beta.
fn softplus_beta(x: f32, beta: f32) -> f32 {
    let z = beta * x;
    if (z > 20.0) { return x; }
    return log(1.0 + exp(z)) / beta;
}

fn sigmoid(x: f32) -> f32 {
    if (x >= 0.0) { return 1.0 / (1.0 + exp(-x)); }
    let e = exp(x);
    return e / (1.0 + e);
}
