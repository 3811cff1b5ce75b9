//! Min-max normalisation of actions and low-dimensional observations to [-1, 1] from the
//! training data's statistics (stored in the checkpoint). A dimension whose range is below
//! [`MIN_RANGE`] (a constant joint, an unused gripper) is left unscaled rather than blown up.
//!
//! The arithmetic is LeRobot's (`2 (x - min) / (max - min) - 1` and back), and statistics
//! imported from LeRobot keep its zero-range rule (divide by its eps instead), so an imported
//! policy sees exactly the numbers it was trained on.

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
    /// LeRobot's rule for a dimension whose max equals its min: divide by this instead
    /// (imported statistics). Absent: labrig's rule (range < [`MIN_RANGE`] is unscaled).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub zero_range_eps: Option<f32>,
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
                None => stats = Some(MinMax { min: values.to_vec(), max: values.to_vec(), zero_range_eps: None }),
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

    /// Per dimension the (low, range) of `2 (x - low) / range - 1`: [min, max] -> [-1, 1], or
    /// (-1, 2), the identity, for a dimension left unscaled.
    fn affine(&self, like: &Tensor) -> (Tensor, Tensor) {
        let (low, range): (Vec<f32>, Vec<f32>) = self
            .min
            .iter()
            .zip(&self.max)
            .map(|(&lo, &hi)| {
                let range = hi - lo;
                match self.zero_range_eps {
                    Some(eps) => (lo, if range == 0.0 { eps } else { range }),
                    None if range < MIN_RANGE => (-1.0, 2.0),
                    None => (lo, range),
                }
            })
            .unzip();
        let t = |v: Vec<f32>| Tensor::from_slice(&v).to_kind(like.kind()).to_device(like.device());
        (t(low), t(range))
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
        let (low, range) = self.affine(x);
        Ok((x - low) * 2.0 / range - 1.0)
    }

    /// The inverse of [`MinMax::normalize`] (a policy's actions back to the robot's units).
    pub fn unnormalize(&self, y: &Tensor) -> Result<Tensor, NormalizeError> {
        self.check(y)?;
        let (low, range) = self.affine(y);
        Ok((y + 1.0) / 2.0 * range + low)
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
        // LeRobot's rule, for imported statistics: a zero range divides by eps, so the
        // constant maps to -1 and back to itself.
        let lerobot = MinMax { min: vec![0.25], max: vec![0.25], zero_range_eps: Some(1e-8) };
        let y = lerobot.normalize(&Tensor::from_slice(&[0.25f32])).unwrap();
        assert_eq!(f32::try_from(&y.get(0)).unwrap(), -1.0);
        assert_eq!(f32::try_from(&lerobot.unnormalize(&Tensor::from_slice(&[0.3f32])).unwrap().get(0)).unwrap(), 0.25);
    }

    #[test]
    fn bad_data_is_named() {
        assert_eq!(MinMax::fit(std::iter::empty()).unwrap_err(), NormalizeError::Empty);
        let ragged: Vec<&[f32]> = vec![&[1.0, 2.0], &[1.0]];
        assert_eq!(MinMax::fit(ragged).unwrap_err(), NormalizeError::Ragged { row: 1, got: 1, want: 2 });
        let nan: Vec<&[f32]> = vec![&[1.0, 2.0], &[1.0, f32::NAN]];
        assert!(matches!(MinMax::fit(nan).unwrap_err(), NormalizeError::NotFinite { row: 1, dim: 1, .. }));
        let mm = MinMax { min: vec![0.0; 3], max: vec![1.0; 3], zero_range_eps: None };
        assert_eq!(
            mm.normalize(&Tensor::zeros([2, 4], (Kind::Float, tch::Device::Cpu))).unwrap_err(),
            NormalizeError::Width { stats: 3, got: 4 }
        );
    }
}
