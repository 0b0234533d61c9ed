"""`lab recover FILE [-o OUT]` and `lab review RUN.mcap [--save out.rrd]` (docs/recording.md)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser("recover", help="rewrite a run file left without its footer (killed run) into a readable one")
    r.add_argument("file", help="the .mcap file to recover")
    r.add_argument("-o", "--output", help="output file (default: FILE with .recovered.mcap)")
    r.add_argument("--force", action="store_true", help="overwrite the output file if it exists")
    r.set_defaults(func=_recover)

    v = sub.add_parser("review", help="open a run in Rerun: design structure, tag poses, camera path, plots",
                       description="Open a run in Rerun, laid out to read: the 3D structure, the camera image with "
                                   "its detections, the verdicts and grouped plots. With a display a local viewer "
                                   "opens; without one (DISPLAY and WAYLAND_DISPLAY unset) the web viewer is served "
                                   "on 127.0.0.1 and its URL printed, until Ctrl-C.")
    v.add_argument("file", help="the run's .mcap file (a file cut short by a kill works too)")
    where = v.add_mutually_exclusive_group()
    where.add_argument("--save", metavar="RRD", help="write an .rrd file instead of starting a viewer")
    where.add_argument("--web", action="store_true",
                       help="serve the web viewer on 127.0.0.1 even where there is a display")
    where.add_argument("--connect", metavar="URL",
                       help="send to a viewer that is already running (rerun+http://HOST:PORT/proxy or HOST:PORT)")
    v.set_defaults(func=_review)


def _recover(args: argparse.Namespace) -> int:
    from lab.core.recorder.recover import recover

    rep = recover(args.file, args.output, overwrite=args.force)
    if rep.intact:
        print(f"{args.file} is complete and intact ({rep.steps_completed} steps completed): nothing to recover, "
              f"no file written")
        return 0
    if rep.damaged:
        state = f"is damaged in {len(rep.damaged)} place{'s' if len(rep.damaged) > 1 else ''} ({'; '.join(rep.damaged)})"
        if not rep.was_complete:
            state += f" and has no footer ({rep.stop_reason})"
    else:
        state = f"had no footer ({rep.stop_reason})" if not rep.was_complete else "was complete"
    print(f"{args.file} {state}")
    print(f"kept {rep.messages} messages, {rep.steps_completed} steps completed"
          + (f", step {rep.interrupted_step} was interrupted" if rep.interrupted_step else "")
          + (f"; {rep.lost_messages} messages lost with their channel definitions" if rep.lost_messages else "")
          + (f"; dropped {rep.dropped_bytes} bytes not in any intact record" if rep.dropped_bytes else ""))
    if not rep.had_stop:
        print("the run had no stop record; added one: result failed, recovered")
    print(f"wrote {rep.path_out}")
    return 0


def _review(args: argparse.Namespace) -> int:
    from pathlib import Path

    from lab.core.errors import UserError
    from lab.core.review import review
    from lab.core.viewer import choose_mode, wait_for_interrupt

    if not Path(args.file).is_file():
        raise UserError(f"{args.file}: no such file")
    if args.save:
        from lab.core.paths import check_output_file

        check_output_file(args.save, "--save")      # before the run is read, not after
    if args.connect:
        from lab.core.viewer import check_connect_url

        check_connect_url(args.connect)
    rep = review(args.file, args.save, mode=choose_mode(args.save, args.connect, args.web), connect=args.connect)
    try:
        print(f"{rep.path}: {rep.messages} messages, {rep.steps} steps completed, result {rep.result}")
        print(f"design: {rep.design or 'none (no structure recorded or named in the start record)'}")
        if rep.scan.stop_reason:
            print(f"note: the file was cut short ({rep.scan.stop_reason}); showing every complete record")
        print(f"recording id: {rep.recording_id}")
        print(rep.sink.description, flush=True)
        if rep.sink.web is not None:
            print("Ctrl-C stops the web viewer", flush=True)
            wait_for_interrupt(rep.sink.web)
    except KeyboardInterrupt:
        # Ctrl-C is how a served review ends, whenever it comes once the URL is out
        if rep.sink.web is not None:
            rep.sink.web.stop()
    return 0
