//! The command line's names for the library's choices. `clap` stays in this crate: each choice is
//! mirrored here as a `ValueEnum` (its variants and their help) and converted into the library's
//! type, which knows nothing of command lines.

/// A `clap::ValueEnum` mirror of a library enum of unit variants, with `From` both ways.
macro_rules! value_enum {
    ($(#[$meta:meta])* $name:ident => $target:path { $($(#[$vmeta:meta])* $variant:ident),+ $(,)? }) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
        pub enum $name {
            $($(#[$vmeta])* $variant),+
        }

        impl From<$name> for $target {
            fn from(choice: $name) -> $target {
                match choice {
                    $($name::$variant => <$target>::$variant),+
                }
            }
        }

        impl From<$target> for $name {
            fn from(value: $target) -> $name {
                match value {
                    $(<$target>::$variant => $name::$variant),+
                }
            }
        }
    };
}

value_enum! {
    /// Which recognizer makes the templates.
    Recognizer => facegate_vision::recognize::RecognizerKind {
        /// dlib's face embedding alone (`deep.bin` over `embedding.bin`).
        #[value(name = "deep", alias = "dlib")]
        Dlib,
        /// Pixels + LBP through Direct LDA (`dlda.bin`): no third-party weights, less CPU.
        Classical,
        /// OpenCV Zoo's SFace network alone (`sface.bin` over `sface.onnx`).
        Sface,
        /// dlib's network and SFace, their cosines weighted (`fusion.bin`): the default, the most accurate.
        Fusion,
        /// Your own ONNX network (`custom.bin`: `facegate convert onnx-embedding`, then `facegate train embedding`).
        Custom,
    }
}

value_enum! {
    /// Which detector to run.
    Detector => facegate_detect::DetectorKind {
        /// OpenCV Viola–Jones Haar cascades (frontal, then profile and mirrored profile).
        Haar,
        /// SeetaFace funnel-structured cascade through the `rustface` crate.
        Seeta,
        /// YuNet, a multi-view CNN with five key points (OpenCV Zoo, run through `tract`).
        Yunet,
    }
}

value_enum! {
    /// What the service does with a face's liveness (a live face or a printed photo of one).
    Liveness => facegate_service::LivenessPolicy {
        /// No liveness model is run and responses carry no `liveness`.
        Off,
        /// Every face reports its `liveness`; nothing is refused.
        Report,
        /// Enrolment, verify and identify refuse a face taken for an attack (422 `presentation-attack`).
        Enforce,
    }
}

value_enum! {
    /// When the Haar detector also runs the profile cascade.
    Profile => facegate_detect::ProfileMode {
        /// Frontal cascade only.
        Off,
        /// Profile cascades only when the frontal one finds nothing (cheap on frontal photos).
        Fallback,
        /// Always run the profile cascades too and merge.
        Always,
    }
}

value_enum! {
    /// Where the centres of a photo come from.
    CentreOrigin => facegate_research::train_dlda::CentreOrigin {
        /// IMM `.asf` annotations where present, else the automatic front end (detector + ASM, or
        /// detector-box centres while the ASM is not available).
        Annotated,
        /// The automatic front end for every photo.
        Pipeline,
    }
}

value_enum! {
    /// Named regions of the normalized crop.
    Region => facegate_research::train_dlda::FaceRegion {
        /// Both eyes and brows.
        Eyes,
        /// The nose, between and below the eyes.
        Nose,
        /// The mouth and chin.
        Mouth,
        /// Everything above the nose tip (eyes, brows, forehead).
        Upper,
        /// Everything below the eyes (nose, cheeks, mouth).
        Lower,
        /// The central face without the outline (eyes to mouth).
        Inner,
        /// The eye and brow on the image's left.
        LeftEye,
        /// The eye and brow on the image's right.
        RightEye,
        /// The image's left half of the face.
        LeftHalf,
        /// The image's right half of the face.
        RightHalf,
    }
}
