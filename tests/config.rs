//! Every shipped config loads; a bad one is refused with the file, the key and the value.

use crate::common;

use common::repo_path;
use rigbridge::rig::{ConfigError, load_rig};
use std::path::Path;

#[test]
fn every_shipped_rig_config_loads() {
    let mut loaded = 0;
    for entry in std::fs::read_dir(repo_path("config")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let text = std::fs::read_to_string(&path).unwrap();
            if text.contains("[[joint]]") {
                load_rig(&path).unwrap_or_else(|e| panic!("{e}"));
                loaded += 1;
            }
        }
    }
    assert!(loaded >= 1);
}

fn write_variant(name: &str, edit: impl Fn(String) -> String) -> std::path::PathBuf {
    let original = std::fs::read_to_string(repo_path("config/irb120.toml")).unwrap();
    let dir = std::env::temp_dir().join(format!("rigbridge-config-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, edit(original)).unwrap();
    path
}

#[test]
fn unknown_key_names_file_and_key() {
    let path = write_variant("unknown.toml", |t| {
        t.replacen(
            "kind = \"revolute\"",
            "kind = \"revolute\"\nmax_torque = 3.0",
            1,
        )
    });
    let message = load_rig(&path).unwrap_err().to_string();
    assert!(message.contains("unknown.toml"), "{message}");
    assert!(message.contains("max_torque"), "{message}");
}

#[test]
fn inverted_limits_name_key_and_value() {
    let path = write_variant("inverted.toml", |t| {
        t.replacen("upper_deg = 70.0", "upper_deg = -120.0", 1)
    });
    match load_rig(&path).unwrap_err() {
        ConfigError::Invalid {
            file, key, value, ..
        } => {
            assert!(file.ends_with("inverted.toml"));
            assert_eq!(key, "joint[2].upper_deg");
            assert_eq!(value, "-120.0");
        }
        other => panic!("expected Invalid, got {other}"),
    }
}

#[test]
fn wrong_unit_for_the_joint_kind_is_refused() {
    let path = write_variant("units.toml", |t| {
        t.replacen("lower_deg = -165.0", "lower_m = -165.0", 1)
    });
    let message = load_rig(&path).unwrap_err().to_string();
    assert!(message.contains("joint[0].lower_m"), "{message}");
}

#[test]
fn missing_file_is_an_io_error_naming_it() {
    let error = load_rig(Path::new("config/does-not-exist.toml")).unwrap_err();
    assert!(matches!(error, ConfigError::Io { .. }));
    assert!(error.to_string().contains("does-not-exist.toml"));
}

#[test]
fn malformed_urdf_is_an_error_not_a_panic() {
    let path = write_variant("broken.urdf", |_| "<robot name=\"x\"><joint".to_string());
    assert!(load_rig(&path).is_err());
}

#[test]
fn the_shipped_run_settings_load() {
    let settings =
        rigbridge::daemon::config::load_run_settings(&repo_path("config/rigbridge.toml"))
            .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(settings.rig.name, "irb120");
    assert_eq!(settings.config.stream.link, "loopback");
}

#[test]
fn the_shipped_sloth_and_gait_run_settings_load() {
    let settings = rigbridge::daemon::config::load_run_settings(&repo_path("config/gait-run.toml"))
        .unwrap_or_else(|e| panic!("{e}"));
    let sloth = rigbridge::apps::gait::sloth_of(settings.app_rig.as_deref())
        .expect("a gait job loads the sloth");
    assert_eq!(settings.rig.dof(), sloth.dof());
}

#[test]
fn the_shipped_forest_loads() {
    let sloth = rigbridge::apps::gait::SlothRig::load(&repo_path("config/sloth.toml"))
        .unwrap_or_else(|e| panic!("{e}"));
    let forest = rigbridge::apps::gait::Forest::load(
        &repo_path("config/forest.toml"),
        sloth.gait.trunk_tilt_rad,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert!(forest.walk_names().count() >= 3);
}

#[test]
fn a_limit_beyond_the_wire_range_is_refused_when_the_rig_loads() {
    // ±1e7 rad does not fit an i32 of µrad (±2147.48 rad): no target could be sent.
    let path = write_variant("huge.toml", |t| {
        t.replacen("upper_deg = 165.0", "upper_deg = 572957795.0", 1)
    });
    match load_rig(&path).unwrap_err() {
        ConfigError::Invalid { key, reason, .. } => {
            assert_eq!(key, "joint[0].upper_deg");
            assert!(reason.contains("wire range"), "{reason}");
        }
        other => panic!("expected Invalid, got {other}"),
    }
}

/// Issue 19: the stream period is a `Duration`; for every shipped run settings file its
/// seconds are bit for bit the `1 / rate_hz` the code used before, and the twin's delay
/// and the reconnect timeout are the milliseconds and seconds the file says.
#[test]
fn the_shipped_periods_are_the_same_seconds_as_durations() {
    for file in [
        "config/rigbridge.toml",
        "config/gait-run.toml",
        "config/paint-run.toml",
        "config/protocol-paint.toml",
    ] {
        let settings = rigbridge::daemon::config::load_run_settings(&repo_path(file))
            .unwrap_or_else(|e| panic!("{e}"));
        let stream = &settings.config.stream;
        let period = settings.period();
        assert_eq!(
            period.as_secs_f64().to_bits(),
            (1.0 / stream.rate_hz).to_bits(),
            "{file}: {} Hz",
            stream.rate_hz
        );
        assert_eq!(
            period.as_nanos(),
            (1e9 / stream.rate_hz) as u128,
            "{file}: whole ns"
        );
        let delay_ms = settings.config.twin.delay_ms;
        assert_eq!(
            settings.twin_delay().as_secs_f64().to_bits(),
            (delay_ms / 1000.0).to_bits(),
            "{file}: delay {delay_ms} ms"
        );
        assert_eq!(
            settings.reconnect_timeout().as_secs_f64(),
            stream.reconnect_timeout_s,
            "{file}"
        );
    }
}

#[test]
fn every_shipped_cell_loads_and_fits_the_irb120() {
    let rig = load_rig(&repo_path("config/irb120.toml")).unwrap();
    let mut loaded = 0;
    for entry in std::fs::read_dir(repo_path("config")).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        if name.starts_with("cell-") && name.ends_with(".toml") {
            let cell = rigbridge::cell::load_cell(&path).unwrap_or_else(|e| panic!("{e}"));
            rigbridge::cell::CollisionModel::new(&rig, &cell).unwrap_or_else(|e| panic!("{e}"));
            loaded += 1;
        }
    }
    assert!(loaded >= 4, "{loaded}");
}

/// The demo run settings with `cell = ...` replaced by `cell_text`, the rig named by its
/// absolute path so the copy loads from a temporary directory.
fn settings_with_cell(name: &str, cell_text: &str) -> std::path::PathBuf {
    let original = std::fs::read_to_string(repo_path("config/rigbridge.toml")).unwrap();
    let rig = repo_path("config/irb120.toml");
    let text = original
        .replacen(
            "rig = \"irb120.toml\"",
            &format!("rig = {:?}", rig.display().to_string()),
            1,
        )
        .replacen("cell = \"cell-star.toml\"\n", "", 1);
    // A top-level key goes before the first table; a section at the end.
    let text = if cell_text.starts_with("cell = ") {
        text.replacen("[stream]", &format!("{cell_text}\n\n[stream]"), 1)
    } else {
        text + cell_text
    };
    let dir = std::env::temp_dir().join(format!("rigbridge-cell-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn the_cell_setting_is_a_file_or_a_section_and_errors_name_key_and_value() {
    use rigbridge::daemon::config::load_run_settings;
    // No cell key: the built-in floor.
    let none = load_run_settings(&settings_with_cell("none.toml", "")).unwrap();
    assert_eq!(none.cell, rigbridge::cell::Cell::builtin());
    // A [cell] section.
    let section = "\n[cell]\nmargin_m = 0.02\n[[cell.object]]\nname = \"table\"\nshape = \"box\"\nsize_m = [1.0, 1.0, 0.1]\norigin_xyz_m = [0.5, 0.0, -0.05]\n";
    let loaded = load_run_settings(&settings_with_cell("section.toml", section)).unwrap();
    assert_eq!(loaded.cell.margin_m, 0.02);
    assert_eq!(loaded.collision.margin(), 0.02);
    assert!(loaded.collision.body_id("table").is_some());
    // A margin out of range, in the section: file, key and value.
    let bad = section.replace("margin_m = 0.02", "margin_m = 5.0");
    let path = settings_with_cell("bad-margin.toml", &bad);
    let message = load_run_settings(&path).unwrap_err().to_string();
    assert!(
        message.contains("bad-margin.toml: key `cell.margin_m` = 5.0: must lie in [0.001, 1]"),
        "{message}"
    );
    // Neither a file name nor a section.
    let path = settings_with_cell("number.toml", "cell = 42");
    let message = load_run_settings(&path).unwrap_err().to_string();
    assert!(message.contains("key `cell` = 42"), "{message}");
    // A file that is not there: named with where it was looked for.
    let path = settings_with_cell("missing.toml", "cell = \"no-such-cell.toml\"");
    let message = load_run_settings(&path).unwrap_err().to_string();
    assert!(message.contains("no-such-cell.toml"), "{message}");
}

#[test]
fn a_bad_body_names_its_key_and_value() {
    let path = write_variant("bad-body.toml", |t| {
        t.replacen("radius_m = 0.07", "radius_m = -0.07", 1)
    });
    let message = load_rig(&path).unwrap_err().to_string();
    assert!(
        message.contains("key `body[1].collision[0].radius_m` = -0.07: must be a positive number"),
        "{message}"
    );
    let path = write_variant("bad-pair.toml", |t| {
        t.replacen("[\"link_5\", \"link_6\"]", "[\"link_5\", \"link_7\"]", 1)
    });
    let message = load_rig(&path).unwrap_err().to_string();
    assert!(
        message.contains("key `allowed_pairs[9]` = \"link_7\": names no body"),
        "{message}"
    );
}
