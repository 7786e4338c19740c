// The playback bar (`companion dashboard --play FILE.mcap`): shown only when the hub's status
// carries a `playback` state (companion/dashboard/playback.py). Its controls POST a request to
// /playback; the answer, and every status after it, is the player's state. Times are the
// recording's daemon clock, seconds; the bar shows them from the recording's start.

import { fmt } from "./dom.js";

export class PlaybackBar {
  constructor({ bar, toggle, seek, time, speed, file }) {
    Object.assign(this, { bar, toggle, seek, time, speed, file });
    this.state = null; // the player's last state
    this.at = 0; // performance.now() when it arrived
    this.dragging = false; // the user holds the slider: do not move it under them
    toggle.addEventListener("click", () => this.send({ action: this.state?.playing ? "pause" : "play" }));
    seek.addEventListener("input", () => {
      this.dragging = true;
      this.showTime(Number(seek.value));
    });
    seek.addEventListener("change", () => {
      this.dragging = false;
      this.send({ action: "seek", t: Number(seek.value) });
    });
    speed.addEventListener("change", () => this.send({ action: "speed", speed: Number(speed.value) }));
  }

  /** A new player state (from a status event or an answer); null: not a playback. */
  update(state) {
    if (!state) return;
    if (!this.state) {
      this.bar.hidden = false;
      this.speed.replaceChildren(...state.speeds.map((x) => new Option(`${x}×`, String(x))));
      this.seek.min = String(state.start);
      this.seek.max = String(state.end);
      this.file.textContent = `${state.file}: ${state.messages} telemetry messages`;
      document.title = `UAV companion: playing ${state.file}`;
    }
    this.state = state;
    this.at = performance.now();
    this.render();
  }

  /** How fast the recording's clock runs against the page's (1 live, 0 paused). */
  rate() {
    if (!this.state) return 1;
    return this.state.playing ? this.state.speed : 0;
  }

  /** The playback position now (s), from the last state and the time since. */
  position() {
    const s = this.state;
    return Math.min(s.end, s.t + ((performance.now() - this.at) / 1000) * this.rate());
  }

  render() {
    const s = this.state;
    if (!s) return;
    const t = this.position();
    this.toggle.textContent = s.playing ? "pause" : s.ended ? "play again" : "play";
    this.bar.dataset.playing = String(s.playing);
    if (!this.dragging) {
      this.seek.value = String(t);
      this.showTime(t);
    }
    if (document.activeElement !== this.speed) this.speed.value = String(s.speed);
  }

  showTime(t) {
    const s = this.state;
    this.time.textContent = `${fmt(t - s.start, 1)} s / ${fmt(s.end - s.start, 1)} s`;
    this.time.dataset.t = String(t);
  }

  async send(request) {
    try {
      const answer = await fetch("/playback", { method: "POST", headers: { "Content-Type": "application/json" },
        body: JSON.stringify(request) });
      if (answer.ok) this.update(await answer.json());
    } catch {
      // the dashboard is gone: the server badge says so
    }
  }
}
