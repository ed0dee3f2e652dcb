use super::*;

fn projection(input_dims: usize, dims: usize, seed: u32) -> Dlda {
    // A fixed pseudo-random projection (what is tested is the fusion, not the training).
    let value = |i: usize| (((i as u32).wrapping_mul(2654435761).wrapping_add(seed.wrapping_mul(40503)) >> 8) % 1000) as f32 / 500.0 - 1.0;
    Dlda {
        input_dims,
        dims,
        mean: vec![0.0; input_dims],
        projection: (0..input_dims * dims).map(value).collect(),
        within_eigenvalues: vec![1.0; dims],
    }
}

/// Saves `model` as the `dlda.bin` of the models folder `dir` and loads the folder back, as the
/// service does.
fn save_and_load(model: &ClassicalModel, dir: &Path) -> Result<ClassicalRecognizer, RecognizeError> {
    model.save(&dir.join(MODEL_FILE)).unwrap();
    ClassicalRecognizer::load(dir)
}

/// Local parts: each region's projection reads its own features, and the cosine of two
/// templates is the weighted sum of the whole face's and the regions' cosines per path; the
/// version changes with the parts, the file round-trips, and inconsistent parts are refused.
#[test]
fn local_parts_score_the_weighted_sum_of_the_regions() {
    let params = NormalizeParams::default();
    let mask = params.mask();
    let kind = FeatureKind::PixelsLbp { grid: 4 };
    let dims = kind.dims(params.width, params.height, &mask);
    let provenance = Provenance::default();
    let plain = ClassicalModel::new(Normalization::TwoD, params.clone(), kind, projection(dims, 6, 1), provenance);
    let (upper, lower) = (Region { x0: 0.0, y0: 0.0, x1: 1.0, y1: 0.5 }, Region { x0: 0.1, y0: 0.5, x1: 0.9, y1: 1.0 });
    let local_dims = |r: &Region| kind.indices_in(params.width, params.height, &mask, r).len();
    let mut with_parts = plain.clone();
    with_parts.parts = vec![
        LocalPart { region: upper, weight: 0.2, projections: vec![projection(local_dims(&upper), 3, 2)] },
        LocalPart { region: lower, weight: 0.3, projections: vec![projection(local_dims(&lower), 4, 3)] },
    ];
    assert_ne!(plain.version(), with_parts.version());
    assert_eq!(with_parts.template_dims(), 13);
    let crop = |k: usize| GrayF32::from_fn(params.width, params.height, |x, y| ((x * (3 + k) + y * (7 + 2 * k)) % 13) as f32);
    let (a, b) = (crop(0), crop(1));
    let recognizer = ClassicalRecognizer::from_model(with_parts.clone());
    let (ta, tb) = (recognizer.template(Views::Single(&a)).unwrap(), recognizer.template(Views::Single(&b)).unwrap());
    let cos = |dlda: &Dlda, indices: Option<Vec<usize>>| {
        let pick = |c: &GrayF32| {
            let f = kind.extract(c, &mask);
            indices.as_ref().map_or(f.clone(), |i| features::gather(&f, i))
        };
        Template::new("v", dlda.project(&pick(&a))).cosine(&Template::new("v", dlda.project(&pick(&b))))
    };
    let indices = |r: &Region| Some(kind.indices_in(params.width, params.height, &mask, r));
    let expected = 0.5 * cos(&with_parts.dlda, None)
        + 0.2 * cos(&with_parts.parts[0].projections[0], indices(&upper))
        + 0.3 * cos(&with_parts.parts[1].projections[0], indices(&lower));
    assert!((ta.cosine(&tb) - expected).abs() < 1e-5, "{} against {expected}", ta.cosine(&tb));
    let dir = std::env::temp_dir().join(format!("facegate-parts-test-{}", std::process::id()));
    let loaded = save_and_load(&with_parts, &dir).unwrap();
    assert_eq!((loaded.model_version(), loaded.template(Views::Single(&a)).unwrap()), (recognizer.model_version(), ta));
    // A part whose projection does not fit its region is refused at load.
    with_parts.parts[1].projections[0] = projection(local_dims(&upper), 4, 3);
    assert!(matches!(save_and_load(&with_parts, &dir), Err(RecognizeError::Model { .. })));
    std::fs::remove_dir_all(&dir).ok();
}

/// Format-2 files (before the local parts) and format-3 files (before the enrolment-size
/// tables) still load: same version, same templates.
#[test]
fn format_2_and_3_models_load_with_their_version() {
    let params = NormalizeParams::default();
    let mask = params.mask();
    let dims = FeatureKind::Pixels.dims(params.width, params.height, &mask);
    let provenance = Provenance {
        centre_source: "imm-annotations".into(),
        train_persons: vec!["imm-04".into()],
        train_images: 1,
        mirrored: true,
        ..Provenance::default()
    };
    let mut model = ClassicalModel::new(Normalization::Morph, params.clone(), FeatureKind::Pixels, projection(dims, 5, 1), provenance);
    model.secondary = Some(SecondaryPath { normalization: Normalization::TwoD, dlda: projection(dims, 4, 2), weight: 0.3 });
    let m = &model;
    // A format-2 file: the same fields in the same order, without the parts (postcard is positional).
    let bytes = postcard::to_stdvec(&(
        2u32,
        &m.normalization,
        &m.normalize,
        &m.features,
        &m.dlda,
        &m.secondary,
        &m.combine,
        &m.cohort,
        &m.calibration,
        &m.provenance,
    ))
    .unwrap();
    let dir = std::env::temp_dir().join(format!("facegate-format2-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join(MODEL_FILE), &bytes).unwrap();
    let loaded = ClassicalRecognizer::load(&dir).unwrap();
    let fresh = ClassicalRecognizer::from_model(model.clone());
    assert_eq!((loaded.model().parts.len(), loaded.model().format), (0, MODEL_FORMAT));
    assert_eq!(loaded.model_version(), fresh.model_version());
    let crop = GrayF32::from_fn(params.width, params.height, |x, y| ((x * 5 + y * 11) % 17) as f32);
    assert_eq!(
        loaded.template(Views::Fused { primary: &crop, secondary: &crop }).unwrap(),
        fresh.template(Views::Fused { primary: &crop, secondary: &crop }).unwrap()
    );
    // A format-3 file: the format-2 fields then the parts, without the enrolment-size tables.
    let mut with_part = model.clone();
    let upper = Region { x0: 0.0, y0: 0.0, x1: 1.0, y1: 0.5 };
    let local = FeatureKind::Pixels.indices_in(params.width, params.height, &mask, &upper).len();
    with_part.parts = vec![LocalPart { region: upper, weight: 0.3, projections: vec![projection(local, 3, 3), projection(local, 2, 4)] }];
    // The format number is one varint byte: the format-2 bytes renumbered, then the parts.
    let format3: Vec<u8> =
        std::iter::once(3u8).chain(bytes[1..].iter().copied()).chain(postcard::to_stdvec(&with_part.parts).unwrap()).collect();
    std::fs::write(dir.join(MODEL_FILE), &format3).unwrap();
    let loaded = ClassicalRecognizer::load(&dir).unwrap();
    assert_eq!((loaded.model().parts.len(), loaded.model().enrolled_calibration.len()), (1, 0));
    assert_eq!(loaded.model_version(), ClassicalRecognizer::from_model(with_part.clone()).model_version());
    // An unknown format is refused with a typed error.
    let mut future = bytes.clone();
    future[0] = 9;
    std::fs::write(dir.join(MODEL_FILE), &future).unwrap();
    assert!(matches!(ClassicalRecognizer::load(&dir), Err(RecognizeError::Model { .. })));
    std::fs::remove_dir_all(&dir).ok();
}

/// A subject with k templates is judged by the table of the largest calibrated size up to k;
/// the tables survive the model file, and tables out of order are refused at load.
#[test]
fn thresholds_follow_the_number_of_enrolled_templates() {
    let params = NormalizeParams::default();
    let dims = FeatureKind::Pixels.dims(params.width, params.height, &params.mask());
    let mut model = ClassicalModel::new(Normalization::TwoD, params, FeatureKind::Pixels, projection(dims, 3, 1), Provenance::default());
    let impostor: Vec<f32> = (0..2000).map(|i| i as f32 / 4000.0).collect();
    let table = |shift: f32| Calibration::from_scores(&[0.9], &impostor.iter().map(|s| s + shift).collect::<Vec<_>>(), &[1e-3], "t");
    model.calibration = table(0.0);
    model.enrolled_calibration =
        vec![EnrolledCalibration { enrolled: 2, calibration: table(0.01) }, EnrolledCalibration { enrolled: 5, calibration: table(0.03) }];
    let recognizer = ClassicalRecognizer::from_model(model.clone());
    let threshold = |k: usize| recognizer.operating_point(1e-3, k).threshold;
    assert!(threshold(1) < threshold(2) && threshold(2) < threshold(5));
    assert_eq!((threshold(0), threshold(3), threshold(4), threshold(9)), (threshold(1), threshold(2), threshold(2), threshold(5)));
    let dir = std::env::temp_dir().join(format!("facegate-enrolled-test-{}", std::process::id()));
    assert_eq!(save_and_load(&model, &dir).unwrap().model(), &model);
    model.enrolled_calibration.swap(0, 1);
    assert!(matches!(save_and_load(&model, &dir), Err(RecognizeError::Model { .. })));
    std::fs::remove_dir_all(&dir).ok();
}

/// A fused model's template is both paths' unit projections, weighted so that the cosine of two
/// templates is the weighted mean of the two paths' cosines; it needs one crop per path.
#[test]
fn fused_templates_score_the_weighted_mean_of_the_paths() {
    let params = NormalizeParams::default();
    let mask = params.mask();
    let dims = FeatureKind::Pixels.dims(params.width, params.height, &mask);
    let provenance = Provenance::default();
    let single = ClassicalModel::new(Normalization::Morph, params.clone(), FeatureKind::Pixels, projection(dims, 5, 1), provenance.clone());
    let mut fused = single.clone();
    fused.secondary = Some(SecondaryPath { normalization: Normalization::TwoD, dlda: projection(dims, 4, 2), weight: 0.3 });
    assert_ne!(single.version(), fused.version());
    assert_eq!((fused.template_dims(), fused.paths()), (9, vec![Normalization::Morph, Normalization::TwoD]));
    let crop = |k: usize| GrayF32::from_fn(params.width, params.height, |x, y| ((x * (3 + k) + y * (7 + 2 * k)) % 13) as f32);
    let (a, b, c, d) = (crop(0), crop(1), crop(2), crop(3));
    let fused = ClassicalRecognizer::from_model(fused);
    assert!(matches!(fused.template(Views::Single(&a)), Err(RecognizeError::Views { expected: 2, found: 1 })));
    let (t1, t2) = (
        fused.template(Views::Fused { primary: &a, secondary: &b }).unwrap(),
        fused.template(Views::Fused { primary: &c, secondary: &d }).unwrap(),
    );
    assert_eq!(t1.vector.len(), 9);
    // The paths' own cosines, from their unit projections.
    let cos = |dlda: &Dlda, x: &GrayF32, y: &GrayF32| {
        let (p, q) = (dlda.project(&FeatureKind::Pixels.extract(x, &mask)), dlda.project(&FeatureKind::Pixels.extract(y, &mask)));
        Template::new("v", p).cosine(&Template::new("v", q))
    };
    let m = fused.model();
    let expected = 0.7 * cos(&m.dlda, &a, &c) + 0.3 * cos(&m.secondary.as_ref().unwrap().dlda, &b, &d);
    assert!((fused.score(&t1, std::slice::from_ref(&t2)) - expected).abs() < 1e-5);
    // Templates of the single-path model are not comparable with the fused ones.
    let single = ClassicalRecognizer::from_model(single);
    let t3 = single.template(Views::Single(&a)).unwrap();
    assert!(fused.try_score(&t1, &[t3.clone()]).is_err());
    assert_eq!(fused.score(&t1, &[t3]), -1.0);
    // The model file round-trips, fusion included.
    let dir = std::env::temp_dir().join(format!("facegate-fused-test-{}", std::process::id()));
    let loaded = save_and_load(fused.model(), &dir).unwrap();
    assert_eq!(
        (loaded.model_version(), loaded.template(Views::Fused { primary: &a, secondary: &b }).unwrap()),
        (fused.model_version(), t1)
    );
    std::fs::remove_dir_all(&dir).ok();
}
