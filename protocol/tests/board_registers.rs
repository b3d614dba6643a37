//! The board's hardware-only registers and their expected values (`BoardRegisters::CHECKS`):
//! the values the firmware sets pass, the chip's reset and factory values fail.

use subsurf_protocol::BoardRegisters;

/// What a board running this firmware reads (the option bytes with BOR_LEV = 0b00 and the
/// factory's other bits, ACR with 5 wait states and the accelerator on, DBGMCU freezing only
/// TIM2 and TIM4, TIM2's update as TRGO, TIM4 clocked by ITR1).
const SET_UP: BoardRegisters = BoardRegisters {
    flash_optcr: 0x0FFF_AAE1,
    flash_acr: 0x0000_0705,
    dbgmcu_apb1_fz: 0x0000_0005,
    dbgmcu_apb2_fz: 0,
    tim2_cr2: 0x0000_0020,
    tim4_smcr: 0x0000_0017,
};

#[test]
fn the_firmware_s_values_pass_every_check() {
    assert!(SET_UP.checks().iter().all(|(_, _, ok)| *ok));
    assert_eq!(BoardRegisters::from_values(SET_UP.values()), SET_UP);
}

#[test]
fn reset_and_factory_values_fail_their_check() {
    let failing = |r: BoardRegisters| -> Vec<&'static str> {
        r.checks()
            .iter()
            .filter(|(_, _, ok)| !ok)
            .map(|(c, _, _)| c.name)
            .collect()
    };
    // The factory option bytes: BOR off (0b11).
    let factory = BoardRegisters {
        flash_optcr: 0x0FFF_AAED,
        ..SET_UP
    };
    assert_eq!(failing(factory), ["FLASH_OPTCR.BOR_LEV"]);
    // embassy's clock set-up alone: wait states, no prefetch, no caches.
    let no_art = BoardRegisters {
        flash_acr: 0x0000_0005,
        ..SET_UP
    };
    assert_eq!(failing(no_art), ["FLASH_ACR.LATENCY/PRFTEN/ICEN/DCEN"]);
    // A probe configuration that freezes the laser timer or the watchdog on halt.
    let frozen = BoardRegisters {
        dbgmcu_apb1_fz: 0x0000_1005,
        dbgmcu_apb2_fz: 0x0000_0002,
        ..SET_UP
    };
    assert_eq!(
        failing(frozen),
        [
            "DBGMCU_APB1_FZ.TIM2/TIM3/TIM4/TIM5/IWDG",
            "DBGMCU_APB2_FZ.TIM8"
        ]
    );
    // TIM4 not clocked by TIM2 (reset values).
    let unwired = BoardRegisters {
        tim2_cr2: 0,
        tim4_smcr: 0,
        ..SET_UP
    };
    assert_eq!(failing(unwired), ["TIM2_CR2.MMS", "TIM4_SMCR.TS/SMS"]);
}

/// The command and its reply cross the link whole, the largest register values included.
#[test]
fn the_command_and_its_reply_round_trip_in_one_frame() {
    use subsurf_protocol::{
        Command, FrameDecoder, MAX_FRAME, Reply, Request, Response, RigMessage, encode_reply,
        encode_request,
    };
    let mut out = [0u8; MAX_FRAME];
    let req = Request {
        seq: 7,
        command: Command::BoardRegisters,
    };
    let n = encode_request(&req, &mut out).unwrap();
    let mut dec = FrameDecoder::new();
    assert_eq!(
        dec.decode::<Request>(&out[..n]).collect::<Vec<_>>(),
        vec![req]
    );
    for registers in [
        Some(BoardRegisters::from_values([u32::MAX; 6])),
        Some(SET_UP),
        None,
    ] {
        let reply = Reply {
            seq: 7,
            result: Ok(Response::BoardRegisters(registers)),
        };
        let n = encode_reply(&reply, &mut out).unwrap();
        assert!(n <= MAX_FRAME);
        let back: Vec<RigMessage> = dec.decode::<RigMessage>(&out[..n]).collect();
        assert_eq!(back, vec![RigMessage::Reply(reply)]);
    }
}
