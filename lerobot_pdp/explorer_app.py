"""The explorer's web page: :class:`~lerobot_pdp.explorer.Explorer`'s panels wired into a Gradio app.

Only wiring lives here (what each control calls, what it updates); the work is in ``explorer.py``. Each event
is also a named API endpoint (``/pick``, ``/select``, ``/interpolate``, ``/fit``, ``/landscape``, ``/save``; and
``/stop_landscape``, which stops the caller's own landscape), so
the app can be driven by ``gradio_client`` as well as by a person. Per-visitor state (the selected latent, the
fitted mark, the drawn path, the map's pixel geometry) is kept in ``gr.State``.

A bad input is an error to a client (its endpoint raises), but on the page it is a message in the summary (and a
toast) with everything else left as it was: Gradio marks every output of a failed event with an "Error" overlay,
which would sit over the latent map and take its clicks. So the page's controls run "soft" twins of the endpoints.
"""

from __future__ import annotations

import functools
import logging
import threading
from dataclasses import asdict
from typing import Any

from .explorer import LANDSCAPE_MAX_ROLLOUTS, Explorer, FitMark, MapImage, Selection, import_gradio

logger = logging.getLogger(__name__)
USER_ERRORS = (ValueError, KeyError, FileNotFoundError, FileExistsError, RuntimeError)


def build_app(explorer: Explorer) -> Any:
    """The explorer as a ``gr.Blocks`` app, queued, not launched (``app.launch()``; a Space runs it as is)."""
    gr = import_gradio()
    # each visitor's "stop" for its landscape (by Gradio's session hash): one visitor's stop is not another's
    stops: dict[str, threading.Event] = {}

    def stop_of(request: Any) -> threading.Event:
        return stops.setdefault(getattr(request, "session_hash", None) or "", threading.Event())

    def _message(e: Exception) -> str:
        message = str(e.args[0] if isinstance(e, KeyError) and e.args else e)
        logger.info("explorer: %s", message)  # one log line in the terminal, not a traceback
        return message

    def user_errors(fn):
        """An endpoint: a bad input is an error a client reads, not a server traceback."""
        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except USER_ERRORS as e:
                raise gr.Error(_message(e), print_exception=False) from e
        return wrapped

    def on_page(fn, message_at: int, n_outputs: int):
        """The page's twin of an endpoint: a bad input is shown in output ``message_at`` (and a toast); the other
        outputs keep what they show, so no error overlay covers the map."""
        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except USER_ERRORS as e:
                message = _message(e)
                gr.Warning(message)
                out = tuple(f"**Not done:** {message}" if i == message_at else gr.skip() for i in range(n_outputs))
                return out if n_outputs > 1 else out[0]
        return wrapped

    def fresh() -> dict:
        return {"selection": None, "fit": None, "path": None, "view": None, "dataset": None, "episode": None}

    def show(state: dict, selection: Selection | None, act: bool = True) -> tuple:
        """Redraw the map with the marks; with a selection, its rollouts (or the decoder's view)."""
        state = {**state, "selection": None if selection is None else asdict(selection)}
        fit = FitMark(**state["fit"]) if state["fit"] else None
        view = explorer.render_map(selection, fit, state["path"])
        state["view"] = {"box": view.box, "xlim": view.xlim, "ylim": view.ylim}
        image, summary = None, "click a point of the map" if selection is None else f"**{selection.source}**"
        if selection is not None and act:
            if explorer.has_env:
                run = explorer.rollout(selection.z)
                image, summary = run.image, f"**{selection.source}**: {run.summary()}"
            elif explorer.decoder_source(state.get("dataset")) is None:  # selected (and savable) all the same
                summary += f"; {explorer.no_recording_note()}"
            else:
                # the episode fitted last (a fit sets both); before any, None: the one the explorer picks
                image = explorer.decoder_view(selection.z, state.get("dataset"), state.get("episode"))
        if selection is not None:
            summary += explorer.far_note(selection.z)
        latent = "" if selection is None else ", ".join(f"{v:.4g}" for v in selection.z)
        return view.image, image, summary, latent, state

    with gr.Blocks(title=f"PDP explorer: {explorer.checkpoint.name}", analytics_enabled=False) as app:  # local: no telemetry
        state = gr.State(fresh())
        gr.Markdown(f"## PDP explorer\n{explorer.describe()}")
        with gr.Row():
            with gr.Column(scale=3):
                gr.Markdown("**Latent map**: click a point to act at its latent")
                # no label drawn over the picture: it would hide the first line of the map's own title
                map_img = gr.Image(label="latent map (click a point)", show_label=False, type="numpy",
                                   interactive=False, elem_id="latent-map")
            with gr.Column(scale=1):
                latent_box = gr.Textbox(label="selected latent z", elem_id="latent")
                go = gr.Button("act at this latent")
                px = gr.Number(label="map pixel x", visible=False)
                py = gr.Number(label="map pixel y", visible=False)
        summary = gr.Markdown(elem_id="summary")
        result_img = gr.Image(label="rollouts in the scene" if explorer.has_env else
                              "decoder's view: action chunks sampled at z", type="numpy", interactive=False,
                              elem_id="result")
        with gr.Accordion("interpolate between two modes", open=True):
            choices = explorer.mode_choices()
            with gr.Row():
                mode_a = gr.Dropdown(choices, value=choices[0], label="mode A")
                mode_b = gr.Dropdown(choices, value=choices[-1], label="mode B")
                path_kind = gr.Radio(["linear", "elliptical"], value="linear", label="path")
            t_slider = gr.Slider(0, 1, value=0.5, step=0.05, label="t (0: mode A, 1: mode B)")
        with gr.Accordion("fit a demonstration", open=True):
            with gr.Row():
                demo_box = gr.Textbox(value=str(explorer.dataset or ""), label="LeRobotDataset folder")
                # no precision=0: the page would round 1.5 to 2 before the checks see it
                demo_episode = gr.Number(value=0, label="episode index")
                fit_steps = gr.Number(value=0, label="fit steps (0: the checkpoint's fit_steps)")
            fit_btn = gr.Button("fit z to this episode")
        if explorer.has_env:
            with gr.Accordion("success landscape over z", open=False):
                with gr.Row():
                    grid = gr.Number(value=5, label="grid points per axis")
                    land_rollouts = gr.Number(value=2, label="rollouts per point")
                with gr.Row():
                    land_btn = gr.Button(f"compute (cached per checkpoint, scene and grid; at most "
                                         f"{LANDSCAPE_MAX_ROLLOUTS} rollouts)")
                    land_stop = gr.Button("stop", scale=0)
                land_img = gr.Image(label="success landscape", type="numpy", interactive=False)
                land_note = gr.Markdown()
        with gr.Accordion("save the selected latent as an adapted checkpoint", open=True):
            out_box = gr.Textbox(label="new checkpoint folder (must not exist)")
            save_btn = gr.Button("save adapted checkpoint")
            save_note = gr.Markdown(elem_id="save-note")

        outputs = [map_img, result_img, summary, latent_box, state]

        def start(state):
            return show(fresh(), None)

        def pick(x, y, state):
            view = state.get("view")
            if view is None:  # a client that never loaded the page: the map as it would show it
                fit = FitMark(**state["fit"]) if state["fit"] else None
                drawn = explorer.render_map(Selection(**state["selection"]) if state["selection"] else None, fit,
                                            state["path"])
                view = {"box": drawn.box, "xlim": drawn.xlim, "ylim": drawn.ylim}
            selection = explorer.pick(MapImage(None, tuple(view["box"]), tuple(view["xlim"]), tuple(view["ylim"])),
                                      float(x), float(y))
            return show(state, selection)

        def on_click(state, evt: gr.SelectData):
            if evt.index is None:
                raise gr.Error("click inside the picture")
            return evt.index[0], evt.index[1]

        on_click.__annotations__ = {"evt": gr.SelectData}  # Gradio reads the class; this module imports it lazily

        def select(latent, state):
            z = explorer.latent(latent)
            return show(state, Selection(z.tolist(), "latent typed in", {"source": "explorer: latent typed in"}))

        def interpolate(a, b, path, t, state):
            selection, line = explorer.interpolate(a, b, t, path)
            return show({**state, "path": line}, selection)

        def fit(dataset, episode, steps, state):
            if steps not in (None, "") and (not float(steps).is_integer() or steps < 0):
                raise ValueError(f"fit steps must be a whole number >= 0 (0: the checkpoint's fit_steps), got {steps}")
            selection, mark = explorer.fit(dataset, episode, int(steps) if steps not in (None, "") and steps > 0 else None)
            # the fitted latent is the selection: an earlier interpolation's path is no longer what the map is about
            return show({**state, "fit": asdict(mark), "path": None, "dataset": str(dataset), "episode": int(episode)},
                        selection)

        def landscape(grid_n, rollouts, request, progress=gr.Progress(), fresh=True):  # noqa: B008 (Gradio's way)
            """``fresh``: a stop from before this call is forgotten (a client's call); the page forgets it at
            the click instead, so that a stop while the landscape waits its turn stops it too."""
            stopping = stop_of(request)
            if fresh:
                stopping.clear()

            def report(fraction: float, what: str) -> None:  # between batches of rollouts: where a stop takes effect
                if stopping.is_set():
                    raise RuntimeError("the landscape was stopped; nothing was cached")
                progress(fraction, desc=what)

            try:
                land = explorer.landscape(grid_n, rollouts, progress=report)
            finally:
                stopping.clear()  # a stop that came after the last batch does not stop the next landscape
            note = (f"{'read from the cache' if land.from_cache else 'computed and cached'}: `{land.cache.name}`; "
                    f"mean success {land.success.mean():.0%}")
            return explorer.landscape_image(land), note

        def page_landscape(grid_n, rollouts, request, progress=gr.Progress()):  # noqa: B008
            return landscape(grid_n, rollouts, request, progress, fresh=False)

        def stop_landscape(request) -> None:
            """Stop the caller's landscape (being computed, or on the page waiting its turn) at its next batch."""
            stop_of(request).set()

        def forget_stop(request) -> None:
            stop_of(request).clear()

        for fn in (landscape, page_landscape, stop_landscape, forget_stop):  # Gradio passes the request by
            fn.__annotations__ = {"request": gr.Request}                       # this class (imported lazily)

        def save(out, state):
            if not state.get("selection"):
                raise ValueError("select a latent first (click the map, interpolate or fit)")
            path = explorer.save_adapted(Selection(**state["selection"]), out)
            return f"wrote `{path}`: load it with `PDPPolicy.from_pretrained` or `--policy.path`"

        at_summary = outputs.index(summary)
        app.load(user_errors(start), [state], outputs, api_name=False)
        map_img.select(on_click, [state], [px, py], api_name=False).then(on_page(pick, at_summary, len(outputs)),
                                                                         [px, py, state], outputs, api_name=False)
        go.click(on_page(select, at_summary, len(outputs)), [latent_box, state], outputs, api_name=False)
        latent_box.submit(on_page(select, at_summary, len(outputs)), [latent_box, state], outputs, api_name=False)
        t_slider.release(on_page(interpolate, at_summary, len(outputs)), [mode_a, mode_b, path_kind, t_slider, state],
                         outputs, api_name=False)
        fit_btn.click(on_page(fit, at_summary, len(outputs)), [demo_box, demo_episode, fit_steps, state], outputs,
                      api_name=False)
        if explorer.has_env:
            land_btn.click(forget_stop, None, None, queue=False, api_name=False).then(
                on_page(page_landscape, 1, 2), [grid, land_rollouts], [land_img, land_note], api_name=False)
            # outside the queue: the landscape it stops holds the app's one turn
            land_stop.click(stop_landscape, None, None, queue=False, api_name=False)
        save_btn.click(on_page(save, 0, 1), [out_box, state], [save_note], api_name=False)
        # the endpoints a client calls (hidden buttons: the page uses the twins above)
        api = {"pick": (pick, [px, py, state], outputs), "select": (select, [latent_box, state], outputs),
               "interpolate": (interpolate, [mode_a, mode_b, path_kind, t_slider, state], outputs),
               "fit": (fit, [demo_box, demo_episode, fit_steps, state], outputs),
               "save": (save, [out_box, state], [save_note])}
        if explorer.has_env:
            api["landscape"] = (landscape, [grid, land_rollouts], [land_img, land_note])
        for name, (fn, inputs, outs) in api.items():
            gr.Button(name, visible=False).click(user_errors(fn), inputs, outs, api_name=name)
        if explorer.has_env:  # outside the queue, as the page's stop button
            gr.Button("stop_landscape", visible=False).click(stop_landscape, None, None, queue=False,
                                                             api_name="stop_landscape")
    app.queue(default_concurrency_limit=1)  # one policy: requests take turns
    return app


def launch(explorer: Explorer, port: int | None = None, share: bool = False, block: bool = True) -> Any:
    """Build and serve the app on ``127.0.0.1:port`` (None: a free port); ``block=False`` returns at once."""
    app = build_app(explorer)
    # Gradio's own lines: with share, the public link; without, advice to call launch(share=True) (on the command
    # line that is --share true, so they are left out)
    app.launch(server_name="127.0.0.1", server_port=port, share=share, prevent_thread_lock=not block,
               show_error=True, quiet=not (block and share))
    return app
