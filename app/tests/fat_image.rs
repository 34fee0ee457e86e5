//! The SD-card read path against real FAT16 and FAT32 images that the test
//! builds itself: an MBR with one partition, formatted by an independent FAT
//! implementation (the `fatfs` crate), read back through embedded-sdmmc.

use embedded_sdmmc::{Block, BlockCount, BlockDevice, BlockIdx};
use onechip_app::config_files::Files;
use onechip_app::sdcard::{PRINTER_CFG, ReadError, SdFiles};
use std::cell::RefCell;
use std::io::{Cursor, Write};

/// Partition start, in 512-byte blocks (1 MiB, as SD formatters align).
const PARTITION_START: u32 = 2048;

/// An SD card in memory.
struct MemCard(RefCell<Vec<u8>>);

#[derive(Debug)]
struct OutOfRange;
impl std::fmt::Display for OutOfRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("block out of range")
    }
}
impl std::error::Error for OutOfRange {}

impl BlockDevice for MemCard {
    type Error = OutOfRange;
    fn read(&self, blocks: &mut [Block], start: BlockIdx) -> Result<(), OutOfRange> {
        let data = self.0.borrow();
        for (i, block) in blocks.iter_mut().enumerate() {
            let at = (start.0 as usize + i) * Block::LEN;
            block
                .contents
                .copy_from_slice(data.get(at..at + Block::LEN).ok_or(OutOfRange)?);
        }
        Ok(())
    }
    fn write(&self, blocks: &[Block], start: BlockIdx) -> Result<(), OutOfRange> {
        let mut data = self.0.borrow_mut();
        for (i, block) in blocks.iter().enumerate() {
            let at = (start.0 as usize + i) * Block::LEN;
            data.get_mut(at..at + Block::LEN)
                .ok_or(OutOfRange)?
                .copy_from_slice(&block.contents);
        }
        Ok(())
    }
    fn num_blocks(&self) -> Result<BlockCount, OutOfRange> {
        Ok(BlockCount((self.0.borrow().len() / Block::LEN) as u32))
    }
}

/// Builds a card image of `mib` MiB whose first partition is a fresh FAT
/// volume of `fat_type` holding `files` in its root directory (or, named
/// `folder/file`, in a folder of it).
fn card(mib: usize, fat_type: fatfs::FatType, files: &[(&str, &[u8])]) -> MemCard {
    let volume_len = mib * 1024 * 1024 - PARTITION_START as usize * 512;
    let mut volume = Cursor::new(vec![0u8; volume_len]);
    let options = fatfs::FormatVolumeOptions::new()
        .fat_type(fat_type)
        .bytes_per_cluster(512);
    fatfs::format_volume(&mut volume, options).expect("format");
    {
        let fs = fatfs::FileSystem::new(&mut volume, fatfs::FsOptions::new()).expect("mount");
        for (name, content) in files {
            let (dir, file) = match name.split_once('/') {
                Some((folder, file)) => (fs.root_dir().create_dir(folder).expect("mkdir"), file),
                None => (fs.root_dir(), *name),
            };
            dir.create_file(file)
                .expect("create")
                .write_all(content)
                .expect("write");
        }
    }
    let mut image = vec![0u8; PARTITION_START as usize * 512];
    let entry = &mut image[446..462];
    entry[4] = match fat_type {
        fatfs::FatType::Fat32 => 0x0c,
        _ => 0x06,
    };
    entry[8..12].copy_from_slice(&PARTITION_START.to_le_bytes());
    entry[12..16].copy_from_slice(&((volume_len / 512) as u32).to_le_bytes());
    image[510] = 0x55;
    image[511] = 0xaa;
    image.extend_from_slice(volume.get_ref());
    MemCard(RefCell::new(image))
}

/// A printer.cfg spanning many clusters, with recognisable content.
fn sample_cfg() -> Vec<u8> {
    let mut cfg = b"[printer]\nkinematics: cartesian\nmax_velocity: 300\n".to_vec();
    for i in 0..400 {
        cfg.extend_from_slice(
            format!("# filler line {i} to cross cluster boundaries\n").as_bytes(),
        );
    }
    cfg
}

#[test]
fn reads_printer_cfg_from_fat16_and_fat32() {
    let cfg = sample_cfg();
    for (mib, fat) in [(8, fatfs::FatType::Fat16), (40, fatfs::FatType::Fat32)] {
        let sd = card(mib, fat, &[("other.txt", b"x"), (PRINTER_CFG, &cfg)]);
        let mut buf = vec![0u8; 64 * 1024];
        let n = SdFiles::new(sd)
            .read(PRINTER_CFG, &mut buf)
            .expect("readable");
        assert_eq!(&buf[..n], &cfg[..], "{fat:?}");
    }
}

#[test]
fn a_missing_file_is_reported_as_not_found() {
    let sd = card(8, fatfs::FatType::Fat16, &[("other.txt", b"x")]);
    let mut buf = [0u8; 128];
    assert!(matches!(
        SdFiles::new(sd).read(PRINTER_CFG, &mut buf),
        Err(ReadError::NotFound)
    ));
}

#[test]
fn a_file_larger_than_the_buffer_is_refused_with_its_size() {
    let cfg = sample_cfg();
    let sd = card(8, fatfs::FatType::Fat16, &[(PRINTER_CFG, &cfg)]);
    let mut buf = [0u8; 1024];
    match SdFiles::new(sd).read(PRINTER_CFG, &mut buf) {
        Err(ReadError::TooLarge {
            size,
            capacity: 1024,
        }) => assert_eq!(size as usize, cfg.len()),
        other => panic!("expected TooLarge, got {other:?}"),
    }
}

#[test]
fn a_blank_card_is_a_filesystem_error_not_a_panic() {
    let sd = MemCard(RefCell::new(vec![0u8; 1024 * 1024]));
    let mut buf = [0u8; 128];
    let err = SdFiles::new(sd)
        .read(PRINTER_CFG, &mut buf)
        .expect_err("no partition table");
    assert!(matches!(err, ReadError::Filesystem(_)), "{err:?}");
    assert!(err.to_string().starts_with("SD card: "));
}

#[test]
fn printer_cfg_and_its_includes_load_from_the_card_folders() {
    use onechip_app::config_files::load;
    use onechip_app::sdcard::SdFiles;
    let printer = b"[include macros/*.cfg]\n[include board.cfg]\n[printer]\n";
    let files: &[(&str, &[u8])] = &[
        ("macros/homing.cfg", b"[gcode_macro H]\n"),
        ("macros/notes.txt", b"not a config"),
        (PRINTER_CFG, printer),
        ("board.cfg", b"[mcu]\nserial: /dev/null\n"),
        ("unused.cfg", b"[fan]\n"),
    ];
    for (mib, fat) in [(8, fatfs::FatType::Fat16), (40, fatfs::FatType::Fat32)] {
        let mut sd = SdFiles::new(card(mib, fat, files));
        let mut buf = vec![0u8; 4096];
        let loaded = load(&mut sd, &mut buf).expect("loads");
        let names: Vec<&str> = loaded.iter().map(|f| f.name).collect();
        assert_eq!(
            names,
            ["printer.cfg", "macros/homing.cfg", "board.cfg"],
            "{fat:?}"
        );
        assert_eq!(loaded[2].text, "[mcu]\nserial: /dev/null\n");
        // A path deeper than one folder is refused with a clear message.
        let mut one = [0u8; 64];
        let e = sd.read("a/b/c.cfg", &mut one).expect_err("too deep");
        assert!(e.to_string().contains("folders in it"), "{e}");
    }
}
