//! The five CANDIDE-3 animation units HoloFace fits (its five blendshapes) and their weights, indexed by
//! unit rather than by a bare position.

use std::ops::{Index, IndexMut};

/// A fitted animation unit, in fit order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Unit {
    /// AUV11, jaw drop (mouth open).
    JawDrop = 0,
    /// AUV2, lip stretcher (smile).
    LipStretcher = 1,
    /// AUV3, brow lowerer (negative: brows raised).
    BrowLowerer = 2,
    /// AUV14, lip-corner depressor.
    LipCornerDepressor = 3,
    /// AUV6, eyes closed.
    EyesClosed = 4,
}

impl Unit {
    /// Every unit, in fit order.
    pub const ALL: [Self; 5] = [
        Self::JawDrop,
        Self::LipStretcher,
        Self::BrowLowerer,
        Self::LipCornerDepressor,
        Self::EyesClosed,
    ];

    /// The unit's name in the CANDIDE-3 `.wfm` file.
    pub const fn candide_name(self) -> &'static str {
        match self {
            Self::JawDrop => "AUV11",
            Self::LipStretcher => "AUV2",
            Self::BrowLowerer => "AUV3",
            Self::LipCornerDepressor => "AUV14",
            Self::EyesClosed => "AUV6",
        }
    }

    /// The snake_case name used in JSON output.
    pub const fn name(self) -> &'static str {
        match self {
            Self::JawDrop => "jaw_drop",
            Self::LipStretcher => "lip_stretcher",
            Self::BrowLowerer => "brow_lowerer",
            Self::LipCornerDepressor => "lip_corner_depressor",
            Self::EyesClosed => "eyes_closed",
        }
    }
}

/// Expression weights, one per [`Unit`] (0 = neutral). The array is in [`Unit::ALL`] order, which is what
/// the C ABI and the solver use.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ExpressionWeights(pub [f64; 5]);

impl ExpressionWeights {
    /// The neutral face.
    pub const NEUTRAL: Self = Self([0.0; 5]);

    /// `(unit, weight)` pairs in fit order.
    pub fn iter(&self) -> impl Iterator<Item = (Unit, f64)> + '_ {
        Unit::ALL.iter().map(|&u| (u, self[u]))
    }
}

impl Index<Unit> for ExpressionWeights {
    type Output = f64;
    fn index(&self, u: Unit) -> &f64 {
        &self.0[u as usize]
    }
}

impl IndexMut<Unit> for ExpressionWeights {
    fn index_mut(&mut self, u: Unit) -> &mut f64 {
        &mut self.0[u as usize]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn units_index_their_own_slot_in_fit_order() {
        let mut w = ExpressionWeights::NEUTRAL;
        w[Unit::BrowLowerer] = -0.4;
        assert_eq!(w.0, [0.0, 0.0, -0.4, 0.0, 0.0]);
        let names: Vec<_> = Unit::ALL.iter().map(|u| u.candide_name()).collect();
        assert_eq!(names, crate::candide::FITTED_UNITS);
        assert_eq!(
            w.iter().map(|(u, _)| u.name()).collect::<Vec<_>>()[3],
            "lip_corner_depressor"
        );
    }
}
