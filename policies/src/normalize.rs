//! Min-max normalisation of actions and low-dimensional observations to [-1, 1] from the
//! training data's statistics (stored in the checkpoint). A dimension whose range is below
//! [`MIN_RANGE`] (a constant joint, an unused gripper) is left unscaled rather than blown up.

use tch::Tensor;

/// Dimensions that vary less than this are passed through unscaled.
pub const MIN_RANGE: f32 = 1e-4;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum NormalizeError {
    #[error("no data to take min-max statistics from")]
    Empty,
    #[error("row {row} has {got} values, the first had {want}")]
    Ragged { row: usize, got: usize, want: usize },
    #[error("row {row}, dimension {dim}: {value} is not a finite number")]
    NotFinite { row: usize, dim: usize, value: f32 },
    #[error("the statistics have {stats} dimensions, the tensor's last dimension is {got}")]
    Width { stats: usize, got: i64 },
}

/// Per-dimension minimum and maximum of the training data.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MinMax {
    pub min: Vec<f32>,
    pub max: Vec<f32>,
}

impl MinMax {
    /// The statistics of `rows` (every row the same width, every value finite).
    pub fn fit<'a>(rows: impl IntoIterator<Item = &'a [f32]>) -> Result<MinMax, NormalizeError> {
        let mut stats: Option<MinMax> = None;
        for (row, values) in rows.into_iter().enumerate() {
            if let Some((dim, &value)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(NormalizeError::NotFinite { row, dim, value });
            }
            match &mut stats {
                None => stats = Some(MinMax { min: values.to_vec(), max: values.to_vec() }),
                Some(s) => {
                    if values.len() != s.min.len() {
                        return Err(NormalizeError::Ragged { row, got: values.len(), want: s.min.len() });
                    }
                    for (i, &v) in values.iter().enumerate() {
                        s.min[i] = s.min[i].min(v);
                        s.max[i] = s.max[i].max(v);
                    }
                }
            }
        }
        stats.ok_or(NormalizeError::Empty)
    }

    pub fn dims(&self) -> usize {
        self.min.len()
    }

    /// y = x * scale + offset per dimension: [min, max] -> [-1, 1], or identity.
    fn affine(&self, like: &Tensor) -> (Tensor, Tensor) {
        let (scale, offset): (Vec<f32>, Vec<f32>) = self
            .min
            .iter()
            .zip(&self.max)
            .map(|(&lo, &hi)| {
                let range = hi - lo;
                if range < MIN_RANGE { (1.0, 0.0) } else { (2.0 / range, -1.0 - 2.0 * lo / range) }
            })
            .unzip();
        let t = |v: Vec<f32>| Tensor::from_slice(&v).to_kind(like.kind()).to_device(like.device());
        (t(scale), t(offset))
    }

    fn check(&self, x: &Tensor) -> Result<(), NormalizeError> {
        let got = x.size().last().copied().unwrap_or(0);
        if got != self.dims() as i64 {
            return Err(NormalizeError::Width { stats: self.dims(), got });
        }
        Ok(())
    }

    /// `x` (any shape, last dimension = the statistics' width) into [-1, 1].
    pub fn normalize(&self, x: &Tensor) -> Result<Tensor, NormalizeError> {
        self.check(x)?;
        let (scale, offset) = self.affine(x);
        Ok(x * scale + offset)
    }

    /// The inverse of [`MinMax::normalize`] (a policy's actions back to the robot's units).
    pub fn unnormalize(&self, y: &Tensor) -> Result<Tensor, NormalizeError> {
        self.check(y)?;
        let (scale, offset) = self.affine(y);
        Ok((y - offset) / scale)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    #[test]
    fn data_maps_to_minus_one_one_and_back() {
        let rows: Vec<Vec<f32>> = vec![vec![0.0, 10.0, 0.5], vec![2.0, -10.0, 0.50005], vec![1.0, 0.0, 0.5]];
        let mm = MinMax::fit(rows.iter().map(Vec::as_slice)).unwrap();
        assert_eq!((mm.min.clone(), mm.max.clone()), (vec![0.0, -10.0, 0.5], vec![2.0, 10.0, 0.50005]));
        let x = Tensor::from_slice(&[0.0f32, 10.0, 0.5, 2.0, -10.0, 0.50005, 1.0, 0.0, 0.5]).view([3, 3]);
        let y = mm.normalize(&x).unwrap();
        let v: Vec<f32> = y.flatten(0, -1).try_into().unwrap();
        // Dimensions 0 and 1 span [-1, 1]; dimension 2's range (5e-5) is below MIN_RANGE: unscaled.
        let want = [-1.0, 1.0, 0.5, 1.0, -1.0, 0.50005, 0.0, 0.0, 0.5];
        for (a, b) in v.iter().zip(want) {
            assert!((a - b).abs() < 1e-6, "{v:?}");
        }
        let back = mm.unnormalize(&y).unwrap();
        assert!((back - &x).abs().max().double_value(&[]) < 1e-5);
    }

    #[test]
    fn bad_data_is_named() {
        assert_eq!(MinMax::fit(std::iter::empty()).unwrap_err(), NormalizeError::Empty);
        let ragged: Vec<&[f32]> = vec![&[1.0, 2.0], &[1.0]];
        assert_eq!(MinMax::fit(ragged).unwrap_err(), NormalizeError::Ragged { row: 1, got: 1, want: 2 });
        let nan: Vec<&[f32]> = vec![&[1.0, 2.0], &[1.0, f32::NAN]];
        assert!(matches!(MinMax::fit(nan).unwrap_err(), NormalizeError::NotFinite { row: 1, dim: 1, .. }));
        let mm = MinMax { min: vec![0.0; 3], max: vec![1.0; 3] };
        assert_eq!(
            mm.normalize(&Tensor::zeros([2, 4], (Kind::Float, tch::Device::Cpu))).unwrap_err(),
            NormalizeError::Width { stats: 3, got: 4 }
        );
    }
}
