//! The GPU check (issue 35): `scripts/gpu-check.sh`, the one command a session with a lent GPU
//! machine runs, and the tests it runs there.
//!
//! - Without a GPU (here, CI) the script must end at once with exit status 2, one line saying
//!   "no GPU", and a figures file saying so: never hang, never build anything.
//! - On a GPU, with the GPU ONNX Runtime (`LEANGATE_EXPECT_CUDA=1`, which the script sets): the
//!   CUDA provider loads, scores the embedded student as the CPU does, and runs in a pipeline;
//!   TensorRT likewise when `LEANGATE_EXPECT_TENSORRT=1` (the script sets it when TensorRT's
//!   libraries are there). Elsewhere these tests print SKIPPED and pass.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use gstleangate::{ExecutionProvider, Precision, Scorer, ScorerOptions};

#[test]
fn without_a_gpu_the_check_exits_2_at_once_saying_so() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let figures = dir.path().join("figures.md");
    let (out, err) = (dir.path().join("stdout"), dir.path().join("stderr"));
    let mut cmd = Command::new("bash");
    cmd.arg(root.join("scripts/gpu-check.sh"))
        .arg(&figures)
        .current_dir(dir.path())
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::fs::File::create(&err).unwrap());
    // On a machine with a GPU (the check runs this test there too), ask a nvidia-smi that is
    // not there; elsewhere the one on PATH, as a user's run would (none here).
    let gpu = Command::new("nvidia-smi")
        .arg("-L")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if gpu {
        cmd.env("LEANGATE_NVIDIA_SMI", "/nonexistent/nvidia-smi");
    } else {
        cmd.env_remove("LEANGATE_NVIDIA_SMI");
    }
    let t = Instant::now();
    let mut child = cmd.spawn().unwrap();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("scripts/gpu-check.sh still running after 60 s without a GPU");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let elapsed = t.elapsed();
    let stderr = std::fs::read_to_string(&err).unwrap();
    let stdout = std::fs::read_to_string(&out).unwrap();
    assert_eq!(status.code(), Some(2), "{stdout}{stderr}");
    assert!(elapsed < Duration::from_secs(20), "took {elapsed:?}");
    assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    assert!(
        stderr.starts_with("gpu-check: no GPU: ") && stderr.contains("nvidia-smi"),
        "{stderr}"
    );
    assert!(stdout.is_empty(), "{stdout}");
    let text = std::fs::read_to_string(&figures).expect("the figures file is written");
    assert!(
        text.contains("- GPU: no GPU (") && text.contains("nvidia-smi"),
        "{text}"
    );
    assert!(
        text.contains("| gpu | skip | ")
            && text.contains("| no GPU: ")
            && text.contains("nothing was measured"),
        "{text}"
    );
    assert!(
        !text.contains("| build |"),
        "nothing runs without a GPU: {text}"
    );
    // The raw log beside it (the figures file names it).
    let log = dir.path().join("figures.log");
    assert!(log.is_file() && text.contains(&log.display().to_string()));
}

fn expects(var: &str) -> bool {
    if std::env::var_os(var).is_some() {
        return true;
    }
    eprintln!("SKIPPED: {var} is not set (no GPU expected here; scripts/gpu-check.sh sets it)");
    false
}

fn load(ep: ExecutionProvider, precision: Precision) -> Scorer {
    Scorer::load(
        &gstleangate::default_model(),
        &ScorerOptions {
            execution_provider: ep,
            precision,
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("{} does not load: {e}", ep.as_str()))
}

/// Utilities of 30 frames of textures (a keep every 5th).
fn utilities(s: &mut Scorer) -> Vec<f32> {
    let spec = s.info().spec.clone();
    let (w, h) = (spec.width as usize, spec.height as usize);
    let pics: Vec<Vec<f32>> = (0..6)
        .map(|k| {
            (0..3 * w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f32, ((i / w) % h) as f32);
                    0.5 + 0.4 * ((x + 3.0 * k as f32) * 0.21).sin() * ((y - k as f32) * 0.13).cos()
                })
                .collect()
        })
        .collect();
    let mut reference = 0;
    (1..=30)
        .map(|i| {
            let u = s.score(&pics[reference], &pics[i % 6]).unwrap();
            if i % 5 == 0 {
                s.on_keep(true);
                reference = i % 6;
            }
            u
        })
        .collect()
}

/// FP32 within 0.02 of the CPU's utilities (TF32 convolutions on the GPU); INT8 within 0.05
/// (the GPU's 8-bit kernels may round differently from the CPU's).
fn agrees_with_the_cpu(ep: ExecutionProvider) {
    for (precision, tolerance) in [(Precision::Fp32, 0.02), (Precision::Int8, 0.05)] {
        let mut gpu = load(ep, precision);
        assert_eq!(gpu.provider(), ep.as_str());
        let a = utilities(&mut load(ExecutionProvider::Cpu, precision));
        let b = utilities(&mut gpu);
        let diff = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        eprintln!("{} {}: max |du| {diff}", ep.as_str(), precision.as_str());
        assert!(
            diff < tolerance,
            "{} {} differs from the CPU by {diff}: {a:?} vs {b:?}",
            ep.as_str(),
            precision.as_str()
        );
    }
}

#[test]
fn cuda_scores_the_embedded_student_as_the_cpu_does() {
    if expects("LEANGATE_EXPECT_CUDA") {
        agrees_with_the_cpu(ExecutionProvider::Cuda);
    }
}

#[test]
fn tensorrt_scores_the_embedded_student_as_the_cpu_does() {
    if expects("LEANGATE_EXPECT_TENSORRT") {
        agrees_with_the_cpu(ExecutionProvider::TensorRt);
    }
}

#[test]
fn auto_chooses_a_gpu_provider() {
    if expects("LEANGATE_EXPECT_CUDA") {
        let s = load(ExecutionProvider::Auto, Precision::Auto);
        let want = if std::env::var_os("LEANGATE_EXPECT_TENSORRT").is_some() {
            "tensorrt"
        } else {
            "cuda"
        };
        assert_eq!(s.provider(), want, "warnings: {:?}", s.warnings);
        assert_eq!(s.info().precision, "fp32", "FP32 on GPU providers");
    }
}

#[test]
fn the_element_runs_on_cuda() {
    if !expects("LEANGATE_EXPECT_CUDA") {
        return;
    }
    let msgs = common::run_pipeline(
        "videotestsrc num-buffers=40 pattern=ball ! video/x-raw,width=640,height=480,framerate=30/1 ! \
         leangate execution-provider=cuda stats-interval=300000000 ! fakesink",
        60,
    );
    assert!(
        common::error_text(&msgs).is_none(),
        "{:?}",
        common::error_text(&msgs)
    );
    let stats: Vec<gstleangate::StatsMessage> = common::element_message(&msgs, "leangate-stats")
        .into_iter()
        .map(|s| gstleangate::StatsMessage::from_structure(s).unwrap())
        .collect();
    let last = stats.last().expect("leangate-stats messages");
    assert_eq!(last.execution_provider, "cuda", "{last:?}");
}

/// A 64-bit ELF file holding the section `name` (`.nv_fatbin` in a CUDA library) = `fatbin` and a
/// section name table, laid out as `scripts/cuda_fatbin_keep.py` reads it: an ELF header, the
/// sections' bytes, then the section header table.
fn elf_with_section(name: &str, fatbin: &[u8]) -> Vec<u8> {
    let names = [b"\0.shstrtab\0".as_slice(), name.as_bytes(), b"\0"].concat();
    let mut f = vec![0u8; 64];
    f[..4].copy_from_slice(b"\x7fELF");
    f[4] = 2; // 64-bit
    f[5] = 1; // little-endian
    f[6] = 1;
    let names_off = f.len();
    f.extend_from_slice(&names);
    while !f.len().is_multiple_of(8) {
        f.push(0);
    }
    let fat_off = f.len();
    f.extend_from_slice(fatbin);
    while !f.len().is_multiple_of(8) {
        f.push(0);
    }
    let shoff = f.len();
    let section = |f: &mut Vec<u8>, name: u32, ty: u32, off: usize, size: usize| {
        let mut h = [0u8; 64];
        h[..4].copy_from_slice(&name.to_le_bytes());
        h[4..8].copy_from_slice(&ty.to_le_bytes());
        h[24..32].copy_from_slice(&(off as u64).to_le_bytes());
        h[32..40].copy_from_slice(&(size as u64).to_le_bytes());
        f.extend_from_slice(&h);
    };
    section(&mut f, 0, 0, 0, 0);
    section(&mut f, 1, 3, names_off, names.len());
    section(&mut f, 11, 1, fat_off, fatbin.len());
    f[0x28..0x30].copy_from_slice(&(shoff as u64).to_le_bytes());
    f[0x3A..0x3C].copy_from_slice(&64u16.to_le_bytes());
    f[0x3C..0x3E].copy_from_slice(&3u16.to_le_bytes());
    f[0x3E..0x40].copy_from_slice(&1u16.to_le_bytes());
    f
}

/// One fatbin container of kernel images `(sm, payload)`: the 16-byte container header, then per
/// image a 64-byte header (kind 2 = cubin, header size, payload size, the architecture at byte 28).
fn fatbin_container(images: &[(u32, Vec<u8>)]) -> Vec<u8> {
    let mut body = Vec::new();
    for (sm, payload) in images {
        let mut h = [0u8; 64];
        h[..2].copy_from_slice(&2u16.to_le_bytes());
        h[4..8].copy_from_slice(&64u32.to_le_bytes());
        h[8..16].copy_from_slice(&(payload.len() as u64).to_le_bytes());
        h[28..32].copy_from_slice(&sm.to_le_bytes());
        body.extend_from_slice(&h);
        body.extend_from_slice(payload);
    }
    let mut c = Vec::new();
    c.extend_from_slice(&0xBA55_ED50u32.to_le_bytes());
    c.extend_from_slice(&1u16.to_le_bytes());
    c.extend_from_slice(&16u16.to_le_bytes());
    c.extend_from_slice(&(body.len() as u64).to_le_bytes());
    c.extend_from_slice(&body);
    c
}

fn run_script(root: &Path, args: &[&std::ffi::OsStr], program: &str) -> std::process::Output {
    Command::new(program)
        .args(args)
        .current_dir(root)
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

#[test]
fn the_cuda_kernel_cut_keeps_the_chosen_architectures_images_and_zeroes_only_the_others() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let script = root.join("scripts/cuda_fatbin_keep.py");
    let image =
        |sm: u32, n: usize| -> Vec<u8> { (0..n).map(|i| (i as u32 * 7 + sm) as u8 | 1).collect() };
    let mut fatbin = fatbin_container(&[(80, image(80, 40)), (90, image(90, 56))]);
    fatbin.extend_from_slice(&[0u8; 8]); // padding between containers
    fatbin.extend_from_slice(&fatbin_container(&[(90, image(91, 24))]));
    fatbin.extend_from_slice(&fatbin_container(&[(120, image(120, 32))]));
    let lib = elf_with_section(".nv_fatbin", &fatbin);
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("lib.so"), dir.path().join("cut.so"));
    std::fs::write(&input, &lib).unwrap();
    // `python3 scripts/cuda_fatbin_keep.py LIB OUT --arch SM`.
    let keep = |lib: &Path, out: &Path, arch: &str| {
        run_script(
            root,
            &[
                script.as_os_str(),
                lib.as_os_str(),
                out.as_os_str(),
                "--arch".as_ref(),
                arch.as_ref(),
            ],
            "python3",
        )
    };
    let o = keep(&input, &out, "90");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        stdout.contains("3 fatbin containers") && stdout.contains("kept sm_90"),
        "{stdout}"
    );
    let cut = std::fs::read(&out).unwrap();
    assert_eq!(cut.len(), lib.len());
    // Every sm_90 image and every header byte as they were; the sm_80 and sm_120 images zeroed.
    let find = |needle: &[u8]| lib.windows(needle.len()).position(|w| w == needle).unwrap();
    for (sm, n, kept) in [
        (80, 40, false),
        (90, 56, true),
        (91, 24, true),
        (120, 32, false),
    ] {
        let at = find(&image(sm, n));
        let want = if kept { image(sm, n) } else { vec![0u8; n] };
        assert_eq!(&cut[at..at + n], &want[..], "image {sm}");
    }
    let differs = lib.iter().zip(&cut).filter(|(a, b)| a != b).count();
    assert_eq!(
        differs,
        40 + 32,
        "only the other architectures' bytes change"
    );

    // Bad input: one line naming the problem, exit 1, nothing written.
    let not_elf = dir.path().join("notes.txt");
    std::fs::write(&not_elf, "not a library").unwrap();
    let plain = dir.path().join("plain.so");
    std::fs::write(&plain, elf_with_section(".text", &fatbin)).unwrap();
    for (input, arch, says) in [
        (&not_elf, "90", "not a 64-bit little-endian ELF file"),
        (&plain, "90", "no .nv_fatbin section"),
        (
            &input,
            "70",
            "no kernels for sm_70 (it has sm_80, sm_90, sm_120)",
        ),
    ] {
        let out = dir.path().join("never.so");
        let o = keep(input, &out, arch);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{stderr}");
        assert!(
            stderr.contains(says) && stderr.lines().count() == 1,
            "{stderr}"
        );
        assert!(!out.exists() && !dir.path().join("never.so.tmp").exists());
    }
}

/// `scripts/gpu-bundle.sh --status` and `--unpack`, as the lent machine runs them: a bundle is
/// unpacked only when every part is there and they make the archive they were cut from.
#[test]
fn a_gpu_bundle_is_unpacked_only_when_every_part_is_there_and_intact() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("repo");
    std::fs::create_dir_all(repo.join("scripts")).unwrap();
    std::fs::copy(
        root.join("scripts/gpu-bundle.sh"),
        repo.join("scripts/gpu-bundle.sh"),
    )
    .unwrap();
    // An archive like the real one (target/release/gpu-bundle.txt first), packed by Python's
    // tarfile (xz), cut in two.
    let stage = dir.path().join("stage");
    std::fs::create_dir_all(stage.join("target/release")).unwrap();
    std::fs::write(
        stage.join("target/release/gpu-bundle.txt"),
        "LeanGate GPU bundle, commit abc\n",
    )
    .unwrap();
    let payload: Vec<u8> = (0..200_000u32)
        .map(|i| (i.wrapping_mul(2654435761) >> 11) as u8)
        .collect();
    std::fs::write(stage.join("target/release/payload.bin"), &payload).unwrap();
    let archive = dir.path().join("bundle.tar.xz");
    let o = Command::new("python3")
        .args(["-c", "import sys, tarfile\nwith tarfile.open(sys.argv[1], 'w:xz') as t: t.add(sys.argv[2] + '/target', 'target')"])
        .arg(&archive)
        .arg(&stage)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bytes = std::fs::read(&archive).unwrap();
    let sha = String::from_utf8(
        Command::new("sha256sum")
            .arg(&archive)
            .output()
            .unwrap()
            .stdout,
    )
    .unwrap();
    let sha = sha.split_whitespace().next().unwrap().to_string();
    let half = bytes.len() / 2;
    let write_part = |n: usize, data: &[u8], sha: &str| {
        let d = repo.join(format!(".gpu-bundle/{n}"));
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join("part"), data).unwrap();
        std::fs::write(
            d.join("index"),
            format!("part {n} of 2\nsha256 {sha}\ncommit abc\n"),
        )
        .unwrap();
    };
    let bundle = |arg: &str| {
        let o = run_script(
            &repo,
            &["scripts/gpu-bundle.sh".as_ref(), arg.as_ref()],
            "bash",
        );
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        );
        (o.status.code(), text)
    };
    let unpacked = repo.join("target/release/payload.bin");

    write_part(1, &bytes[..half], &sha);
    let (code, text) = bundle("--status");
    assert_eq!(code, Some(1), "{text}");
    assert!(
        text.contains("part 1 of 2") && text.contains("parts 2 of 2 missing"),
        "{text}"
    );
    let (code, text) = bundle("--unpack");
    assert_eq!(code, Some(1), "{text}");
    assert!(
        text.contains("parts 2 of 2 missing") && !unpacked.exists(),
        "{text}"
    );

    // A part of another bundle beside it.
    write_part(2, &bytes[half..], &"0".repeat(64));
    let (code, text) = bundle("--unpack");
    assert_eq!(code, Some(1), "{text}");
    assert!(
        text.contains("come from different bundles") && !unpacked.exists(),
        "{text}"
    );

    // Damaged on the way.
    let mut damaged = bytes[half..].to_vec();
    damaged[10] ^= 0x40;
    write_part(2, &damaged, &sha);
    let (code, text) = bundle("--unpack");
    assert_eq!(code, Some(1), "{text}");
    assert!(
        text.contains("sha256 differs") && !unpacked.exists(),
        "{text}"
    );

    write_part(2, &bytes[half..], &sha);
    let (code, text) = bundle("--status");
    assert_eq!(code, Some(0), "{text}");
    assert!(text.contains("complete"), "{text}");
    let (code, text) = bundle("--unpack");
    assert_eq!(code, Some(0), "{text}");
    assert!(
        text.contains("unpacked LeanGate GPU bundle, commit abc"),
        "{text}"
    );
    assert_eq!(std::fs::read(&unpacked).unwrap(), payload);
    let (code, text) = bundle("--bogus");
    assert_eq!(code, Some(1), "{text}");
    assert!(text.contains("unknown argument '--bogus'"), "{text}");
}
