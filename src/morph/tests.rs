use super::*;
use crate::dataset::list_imm;

fn model() -> FaceModel {
    FaceModel::load(&crate::config::sfm_dir()).expect("the Surrey Face Model is in ../shared/models/sfm")
}

#[test]
fn explore_imm_yaw() {
    let m = model();
    let samples = list_imm(&crate::config::shared_dir().join("data/imm")).unwrap();
    for s in samples.iter().filter(|s| s.view <= 4 && s.person <= 6) {
        let pts = s.landmarks().unwrap();
        let f = m.fit(&pts, 640, 480).unwrap();
        eprintln!("{:02}-{} yaw {:6.1} pitch {:6.1} roll {:6.1} res {:.2}", s.person, s.view, f.pose.yaw, f.pose.pitch, f.pose.roll, f.residual_px);
    }
}
