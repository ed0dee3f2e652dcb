//! The 3DMM's views of a training face for the 3D-ASM: which vertex each IMM point sits on per
//! view ([`jaw`]: the jaw follows the visible outline) and a fitted, textured face rendered at
//! another pose with its exact landmarks ([`synth`]). The 3D-ASM's training (`train_asm3d`), the
//! classical recognizer's re-posed training copies and the profile evaluations render with these;
//! the service only reads what they produced (`asm3d.bin`, `asm3d-profile.bin`).

pub mod jaw;
pub mod synth;

pub use jaw::*;
pub use synth::*;
