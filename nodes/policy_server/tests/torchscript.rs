//! TorchScript modules exported by PyTorch itself (tests/fixtures/policies/torchscript_tiny,
//! made by scripts/make_torchscript_fixture.py with torch 2.13: `torch.jit.script` and
//! `torch.jit.trace` of one small policy) loaded through tch's CModule: the same outputs as
//! PyTorch's on the same inputs, and a spec that disagrees with the module is named.

use labrig_msgs::rig::{PolicyObservation, PolicyRequest, RobotState};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::Header;
use labrig_policy_server::serve::Server;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tch::{Kind, Tensor};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/policies/torchscript_tiny")
}

/// The inputs make_torchscript_fixture.py feeds, by its formula (f64, then f32).
fn inputs() -> BTreeMap<String, Tensor> {
    let mut named = BTreeMap::new();
    for (k, cam) in ["wrist", "ext1"].iter().enumerate() {
        let n = 2 * 3 * 64 * 64;
        let v: Vec<f32> = (0..n).map(|i| ((0.001 * i as f64 + k as f64).sin() * 0.5 + 0.5) as f32).collect();
        named.insert(format!("observation.images.{cam}"), Tensor::from_slice(&v).view([1, 2, 3, 64, 64]));
    }
    let state: Vec<f32> = [0.45, 0.02, 0.35, 1.0, 0.0, 0.0, 0.0, 0.1, 0.46, 0.01, 0.34, 0.99, 0.1, 0.0, 0.0, 0.2]
        .map(|x: f64| x as f32)
        .to_vec();
    named.insert("observation.state".into(), Tensor::from_slice(&state).view([1, 2, 8]));
    named
}

#[test]
fn scripted_and_traced_modules_give_pytorchs_outputs() {
    let expected: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fixture().join("expected.json")).unwrap()).unwrap();
    assert_eq!(expected["shape"], serde_json::json!([1, 16, 7]));
    let noise = Tensor::zeros([1, 16, 7], (Kind::Float, tch::Device::Cpu));
    for kind in ["scripted", "traced"] {
        let server =
            Server::load_torchscript(&fixture().join(format!("policy_{kind}.pt")), &fixture().join("spec.toml"))
                .unwrap();
        assert_eq!(server.id(), "torchscript:torchscript_tiny");
        let out = server.predict(&inputs(), &noise, 1).unwrap();
        let got = Vec::<f32>::try_from(out.flatten(0, -1)).unwrap();
        let want: Vec<f64> = serde_json::from_value(expected[kind].clone()).unwrap();
        assert_eq!(got.len(), want.len());
        let worst = got.iter().zip(&want).map(|(g, w)| (f64::from(*g) - w).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-6, "{kind}: differs from PyTorch by up to {worst}");
        // And the module is not a constant: different inputs, different actions.
        let mut other = inputs();
        other.insert("observation.state".into(), Tensor::zeros([1, 2, 8], (Kind::Float, tch::Device::Cpu)));
        let moved = (server.predict(&other, &noise, 2).unwrap() - &out).abs().max().double_value(&[]);
        assert!(moved > 1e-4, "{kind}: the output ignores the state ({moved})");
    }
}

#[test]
fn a_spec_that_disagrees_with_the_module_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let spec = std::fs::read_to_string(fixture().join("spec.toml")).unwrap();
    let short = dir.path().join("short.toml");
    std::fs::write(&short, spec.replace("horizon = 16", "horizon = 12")).unwrap();
    let e = Server::load_torchscript(&fixture().join("policy_scripted.pt"), &short).unwrap_err().to_string();
    assert!(e.contains("the module returned shape [1, 16, 7]; its spec says (1, horizon 12, action_dim 7)"), "{e}");
    let one_cam = dir.path().join("one_cam.toml");
    std::fs::write(&one_cam, spec.replace(r#"cameras = ["wrist", "ext1"]"#, r#"cameras = ["wrist"]"#)).unwrap();
    let e = Server::load_torchscript(&fixture().join("policy_scripted.pt"), &one_cam).unwrap_err().to_string();
    assert!(e.contains("the TorchScript module failed") && e.contains("observation.images.ext1"), "{e}");
    let e =
        Server::load_torchscript(&fixture().join("spec.toml"), &fixture().join("spec.toml")).unwrap_err().to_string();
    assert!(e.contains("not a TorchScript module"), "{e}");
}

/// A request as the loop sends it (JPEG frames, robot states) gives the chunk from the newest
/// observation on: Tp - To + 1 rows, DROID velocities within the module's +-0.2, the gripper
/// in [0, 1].
#[test]
fn a_loop_request_gets_a_chunk_in_the_specs_action_space() {
    let server = Server::load_torchscript(&fixture().join("policy_traced.pt"), &fixture().join("spec.toml")).unwrap();
    let obs = |step: u64| {
        let px: Vec<u8> = (0..96 * 72 * 3).map(|i| ((i * 3 + step as usize) % 251) as u8).collect();
        let jpeg = labrig_episode::jpeg::encode_rgb(&px, 96, 72, 90).unwrap();
        PolicyObservation {
            header: Header { stamp: labrig_msgs::Nanos(step as i64 * 50_000_000).into(), frame_id: "base".into() },
            step_index: step,
            robot_state: RobotState { cartesian_position: [0.45, 0.0, 0.35, 3.1, 0.0, 0.0], ..RobotState::default() },
            images: ["wrist", "ext1"]
                .map(|c| CompressedImage {
                    header: Header { frame_id: c.into(), ..Header::default() },
                    format: "jpeg".into(),
                    data: jpeg.clone(),
                })
                .to_vec(),
            ..PolicyObservation::default()
        }
    };
    let req = PolicyRequest {
        request_id: 3,
        observations: vec![obs(4), obs(5)],
        seed: 1,
        period_ns: 50_000_000,
        ..PolicyRequest::default()
    };
    let c = server.chunk(&req).unwrap();
    assert_eq!((c.horizon, c.action_dim, c.observation_step), (15, 7, 5));
    assert_eq!(c.times_ns[0], 5 * 50_000_000);
    for i in 0..15 {
        let a = c.action(i).unwrap();
        assert!(a[..6].iter().all(|v| v.abs() <= 0.2 + 1e-6), "{a:?}");
        assert!((0.0..=1.0).contains(&a[6]), "{a:?}");
    }
    assert_eq!(server.info()["format"], "torchscript");
    assert_eq!(server.info()["action_space"], "cartesian_velocity");
}
