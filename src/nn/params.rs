//! The parameter store: named host-side f32 tensors with shapes, moved to and from a backend, and
//! checkpoints in the [safetensors](https://github.com/huggingface/safetensors) format (readable
//! from Python with `safetensors.numpy.load_file`).
//!
//! File contents: every tensor as little-endian `F32` under its name; header metadata
//! `pii_bake.format` (= "1"), `pii_bake.order` (JSON list of names in insertion order), and
//! whatever the store's [`ParamStore::metadata`] holds (`config`: the run's config as JSON,
//! `step`: the training step). Optimiser state is stored as ordinary tensors under
//! `optim/<name>/m` and `optim/<name>/v` with `optim/<name>/step` in the metadata
//! ([`ParamStore::put_adam_state`]).
//!
//! Files are written atomically (temporary name, then rename). Reading a missing, truncated or
//! corrupt file, a non-F32 tensor, or (with [`ParamStore::load_into`]) a checkpoint whose names or
//! shapes differ from the model's gives a [`DataError`] naming the file and the tensor.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use crate::backend::{Backend, BackendError, Tensor};
use crate::nn::adam::AdamState;
use crate::util::{atomic_write, DataError};

/// Largest safetensors header (JSON) a checkpoint may declare, in bytes (safetensors' own cap).
pub const MAX_HEADER_BYTES: u64 = 100_000_000;

/// Prefix of optimiser-state tensors.
pub const OPTIM_PREFIX: &str = "optim/";

/// One named tensor (row-major).
#[derive(Clone, Debug, PartialEq)]
pub struct NamedTensor {
    pub name: String,
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// Named f32 tensors in insertion order, plus string metadata.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ParamStore {
    tensors: Vec<NamedTensor>,
    /// Saved in the file header (`config`, `step`, optimiser steps, anything else).
    pub metadata: BTreeMap<String, String>,
}

fn shape_str(s: &[usize]) -> String {
    format!("{s:?}")
}

impl ParamStore {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn len(&self) -> usize {
        self.tensors.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tensors.is_empty()
    }

    pub fn iter(&self) -> impl Iterator<Item = &NamedTensor> {
        self.tensors.iter()
    }

    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.tensors.iter().map(|t| t.name.as_str())
    }

    pub fn get(&self, name: &str) -> Option<&NamedTensor> {
        self.tensors.iter().find(|t| t.name == name)
    }

    fn get_mut(&mut self, name: &str) -> Option<&mut NamedTensor> {
        self.tensors.iter_mut().find(|t| t.name == name)
    }

    fn missing(name: &str) -> BackendError {
        BackendError::Shape(format!("parameter store has no tensor {name:?}"))
    }

    /// Add a new tensor. Errors on a duplicate name, an empty name, or `data.len() != product(shape)`.
    pub fn insert(
        &mut self,
        name: &str,
        shape: &[usize],
        data: Vec<f32>,
    ) -> Result<(), BackendError> {
        if name.is_empty() {
            return Err(BackendError::Shape(
                "parameter store: empty tensor name".into(),
            ));
        }
        if self.get(name).is_some() {
            return Err(BackendError::Shape(format!(
                "parameter store already has a tensor {name:?}"
            )));
        }
        let want = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        if want != Some(data.len()) {
            return Err(BackendError::Shape(format!(
                "tensor {name:?}: {} values for shape {}",
                data.len(),
                shape_str(shape)
            )));
        }
        self.tensors.push(NamedTensor {
            name: name.to_string(),
            shape: shape.to_vec(),
            data,
        });
        Ok(())
    }

    /// Insert, or replace the data and shape of an existing tensor.
    pub fn upsert(
        &mut self,
        name: &str,
        shape: &[usize],
        data: Vec<f32>,
    ) -> Result<(), BackendError> {
        if let Some(i) = self.tensors.iter().position(|t| t.name == name) {
            let old = self.tensors.remove(i);
            if let Err(e) = self.insert(name, shape, data) {
                self.tensors.insert(i, old);
                return Err(e);
            }
            let t = self.tensors.pop().expect("just inserted");
            self.tensors.insert(i, t);
            Ok(())
        } else {
            self.insert(name, shape, data)
        }
    }

    /// The data of a tensor.
    pub fn data(&self, name: &str) -> Option<&[f32]> {
        self.get(name).map(|t| t.data.as_slice())
    }

    /// Replace a tensor's data (same length).
    pub fn set_data(&mut self, name: &str, data: Vec<f32>) -> Result<(), BackendError> {
        let t = self.get_mut(name).ok_or_else(|| Self::missing(name))?;
        if t.data.len() != data.len() {
            return Err(BackendError::Shape(format!(
                "tensor {name:?}: {} values given, shape {} holds {}",
                data.len(),
                shape_str(&t.shape),
                t.data.len()
            )));
        }
        t.data = data;
        Ok(())
    }

    /// Upload a tensor to `backend`.
    pub fn to_backend(&self, backend: &Backend, name: &str) -> Result<Tensor, BackendError> {
        let t = self.get(name).ok_or_else(|| Self::missing(name))?;
        Ok(backend.upload(&t.data))
    }

    /// Copy a backend tensor back into the named host tensor (same length).
    pub fn from_backend(
        &mut self,
        backend: &Backend,
        name: &str,
        tensor: &Tensor,
    ) -> Result<(), BackendError> {
        let data = backend.to_vec(tensor)?;
        self.set_data(name, data)
    }

    /// The `config` metadata entry: the run's configuration as JSON.
    pub fn set_config<C: serde::Serialize>(&mut self, config: &C) -> Result<(), serde_json::Error> {
        self.metadata
            .insert("config".into(), serde_json::to_string(config)?);
        Ok(())
    }

    pub fn config_json(&self) -> Option<&str> {
        self.metadata.get("config").map(String::as_str)
    }

    /// The `config` metadata entry parsed as JSON (None when absent); a malformed entry is a
    /// [`DataError`] naming `path` (the checkpoint the store was loaded from).
    pub fn config_value(&self, path: &Path) -> Result<Option<serde_json::Value>, DataError> {
        self.config_json()
            .map(|c| serde_json::from_str(c).map_err(|e| DataError::new(path, format!("checkpoint config is not valid JSON: {e}"))))
            .transpose()
    }

    pub fn set_step(&mut self, step: u64) {
        self.metadata.insert("step".into(), step.to_string());
    }

    pub fn step(&self) -> Option<u64> {
        self.metadata.get("step").and_then(|s| s.parse().ok())
    }

    /// Store Adam's state for parameter tensor `name` (read back from the backend).
    pub fn put_adam_state(
        &mut self,
        backend: &Backend,
        name: &str,
        state: &AdamState,
    ) -> Result<(), BackendError> {
        let m = backend.to_vec(&state.m)?;
        let v = backend.to_vec(&state.v)?;
        self.upsert(&format!("{OPTIM_PREFIX}{name}/m"), &[m.len()], m)?;
        self.upsert(&format!("{OPTIM_PREFIX}{name}/v"), &[v.len()], v)?;
        self.metadata
            .insert(format!("{OPTIM_PREFIX}{name}/step"), state.step.to_string());
        Ok(())
    }

    /// Adam's state for parameter tensor `name` on `backend`, if stored; its length must match
    /// the parameter tensor when the store has it.
    pub fn adam_state(
        &self,
        backend: &Backend,
        name: &str,
    ) -> Result<Option<AdamState>, BackendError> {
        let (Some(m), Some(v)) = (
            self.get(&format!("{OPTIM_PREFIX}{name}/m")),
            self.get(&format!("{OPTIM_PREFIX}{name}/v")),
        ) else {
            return Ok(None);
        };
        let step_key = format!("{OPTIM_PREFIX}{name}/step");
        let step = self
            .metadata
            .get(&step_key)
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| {
                BackendError::Shape(format!(
                    "optimiser state of {name:?} has no valid {step_key:?} entry"
                ))
            })?;
        if m.data.len() != v.data.len()
            || self.get(name).is_some_and(|p| p.data.len() != m.data.len())
        {
            return Err(BackendError::Shape(format!(
                "optimiser state of {name:?} does not match the parameter's size"
            )));
        }
        Ok(Some(AdamState {
            m: backend.upload(&m.data),
            v: backend.upload(&v.data),
            step,
        }))
    }

    /// Write the store as a safetensors file, atomically.
    pub fn save(&self, path: &Path) -> Result<(), DataError> {
        let bytes: Vec<(String, Vec<u8>, Vec<usize>)> = self
            .tensors
            .iter()
            .map(|t| {
                (
                    t.name.clone(),
                    t.data.iter().flat_map(|v| v.to_le_bytes()).collect(),
                    t.shape.clone(),
                )
            })
            .collect();
        let mut views = Vec::with_capacity(bytes.len());
        for (name, b, shape) in &bytes {
            let view =
                safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape.clone(), b)
                    .map_err(|e| {
                        DataError::new(path, format!("cannot encode tensor {name:?}: {e}"))
                    })?;
            views.push((name.clone(), view));
        }
        let mut meta: HashMap<String, String> = self
            .metadata
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        meta.insert("pii_bake.format".into(), "1".into());
        let order: Vec<&str> = self.names().collect();
        meta.insert(
            "pii_bake.order".into(),
            serde_json::to_string(&order).unwrap_or_default(),
        );
        let encoded = safetensors::serialize(views, Some(meta))
            .map_err(|e| DataError::new(path, format!("cannot encode checkpoint: {e}")))?;
        atomic_write(path, &encoded)
    }

    /// Read a safetensors checkpoint (F32 tensors only). The header length the file declares is
    /// checked against the file's size (and [`MAX_HEADER_BYTES`]) before it is read, and every
    /// tensor's shape against the bytes it spans, so a damaged file is a [`DataError`] naming
    /// the file and the size, never an allocation.
    pub fn load(path: &Path) -> Result<Self, DataError> {
        let bytes = std::fs::read(path)
            .map_err(|e| DataError::new(path, format!("cannot read checkpoint: {e}")))?;
        if bytes.len() < 8 {
            return Err(DataError::new(
                path,
                format!("not a valid safetensors checkpoint: {} bytes, too short for a header", bytes.len()),
            ));
        }
        let declared = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes"));
        let room = (bytes.len() - 8) as u64;
        if declared > room || declared > MAX_HEADER_BYTES {
            return Err(DataError::new(
                path,
                format!(
                    "not a valid safetensors checkpoint: header declares {declared} bytes but the file holds {room} after the length (at most {MAX_HEADER_BYTES} accepted)"
                ),
            ));
        }
        let corrupt = |e: safetensors::SafeTensorError| {
            DataError::new(
                path,
                format!("not a valid safetensors checkpoint (corrupt or truncated): {e}"),
            )
        };
        let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).map_err(corrupt)?;
        let st = safetensors::SafeTensors::deserialize(&bytes).map_err(corrupt)?;
        let mut metadata: BTreeMap<String, String> = header
            .metadata()
            .clone()
            .unwrap_or_default()
            .into_iter()
            .collect();
        metadata.remove("pii_bake.format");
        let order: Vec<String> = metadata
            .remove("pii_bake.order")
            .and_then(|o| serde_json::from_str(&o).ok())
            .unwrap_or_default();
        let mut names: Vec<String> = st.names().into_iter().map(str::to_owned).collect();
        names.sort();
        let rank = |n: &str| order.iter().position(|o| o == n).unwrap_or(usize::MAX);
        names.sort_by_key(|n| rank(n));
        let mut store = ParamStore {
            tensors: Vec::with_capacity(names.len()),
            metadata,
        };
        for name in names {
            let view = st.tensor(&name).map_err(corrupt)?;
            if view.dtype() != safetensors::Dtype::F32 {
                return Err(DataError::new(
                    path,
                    format!(
                        "tensor {name:?} has dtype {:?}; pii-bake checkpoints hold F32 tensors",
                        view.dtype()
                    ),
                ));
            }
            let values = view.shape().iter().try_fold(1usize, |a, &d| a.checked_mul(d));
            if values.and_then(|n| n.checked_mul(4)) != Some(view.data().len()) {
                return Err(DataError::new(
                    path,
                    format!("tensor {name:?}: shape {} does not match its {} bytes", shape_str(view.shape()), view.data().len()),
                ));
            }
            let data: Vec<f32> = view
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            store
                .insert(&name, view.shape(), data)
                .map_err(|e| DataError::new(path, format!("tensor {name:?}: {e}")))?;
        }
        Ok(store)
    }

    /// Load a checkpoint into this store: every tensor of the store must be in the file with the
    /// same shape, and the file may hold no other tensors except optimiser state (`optim/...`).
    /// On any mismatch nothing is changed and the error names the file and the tensor.
    pub fn load_into(&mut self, path: &Path) -> Result<(), DataError> {
        let file = Self::load(path)?;
        for t in &self.tensors {
            match file.get(&t.name) {
                None => {
                    return Err(DataError::new(
                        path,
                        format!(
                            "checkpoint has no tensor {:?} (shape {}) that the model needs",
                            t.name,
                            shape_str(&t.shape)
                        ),
                    ))
                }
                Some(f) if f.shape != t.shape => {
                    return Err(DataError::new(
                        path,
                        format!(
                            "tensor {:?} has shape {} in the checkpoint, the model expects {}",
                            t.name,
                            shape_str(&f.shape),
                            shape_str(&t.shape)
                        ),
                    ))
                }
                Some(_) => {}
            }
        }
        if let Some(extra) = file
            .names()
            .find(|n| !n.starts_with(OPTIM_PREFIX) && self.get(n).is_none())
        {
            return Err(DataError::new(
                path,
                format!("checkpoint has a tensor {extra:?} the model does not have"),
            ));
        }
        let ParamStore { tensors, metadata } = file;
        for ft in tensors {
            match self.get_mut(&ft.name) {
                Some(t) => t.data = ft.data,
                None => self.tensors.push(ft),
            }
        }
        self.metadata.extend(metadata);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn declared_header_length_is_checked_against_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.safetensors");
        let mut s = ParamStore::new();
        s.insert("w", &[2, 3], vec![1.0; 6]).unwrap();
        s.set_config(&serde_json::json!({"a": 1})).unwrap();
        s.save(&p).unwrap();
        let back = ParamStore::load(&p).unwrap();
        assert_eq!(back.config_value(&p).unwrap(), Some(serde_json::json!({"a": 1})));
        let mut b = std::fs::read(&p).unwrap();
        b[..8].copy_from_slice(&(1u64 << 40).to_le_bytes());
        std::fs::write(&p, &b).unwrap();
        let e = ParamStore::load(&p).unwrap_err().to_string();
        assert!(e.contains("c.safetensors") && e.contains(&(1u64 << 40).to_string()), "{e}");
        std::fs::write(&p, &b[..5]).unwrap();
        let e = ParamStore::load(&p).unwrap_err().to_string();
        assert!(e.contains("c.safetensors") && e.contains("too short"), "{e}");
        // overflowing shapes are refused, not multiplied
        assert!(ParamStore::new().insert("x", &[usize::MAX, 2, 0], vec![]).is_err());
    }
}
