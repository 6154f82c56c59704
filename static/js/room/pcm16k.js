// An AudioWorklet that turns the microphone into what the trustlab server's recogniser takes:
// 16 kHz mono 16-bit little-endian PCM, in chunks of 100 ms posted to the page.
//
// The audio graph runs at the device's rate (44.1 or 48 kHz, usually), and not every browser can
// open a 16 kHz context on a microphone, so the worklet downsamples itself: each output sample is
// the mean of the input samples it stands for (a box filter: it keeps the speech band and damps
// what would fold back into it, enough for recognising a yes or a no). Channels are mixed down.

const TARGET_RATE = 16000;
const CHUNK_SAMPLES = 1600; // 100 ms at 16 kHz

class Pcm16kProcessor extends AudioWorkletProcessor {
  constructor() {
    super();
    this.step = sampleRate / TARGET_RATE; // input samples per output sample (may be fractional)
    this.position = 0;
    this.sum = 0;
    this.count = 0;
    this.chunk = new Int16Array(CHUNK_SAMPLES);
    this.filled = 0;
  }

  process(inputs) {
    const channels = inputs[0];
    if (!channels || channels.length === 0) return true;
    const frames = channels[0].length;
    for (let i = 0; i < frames; i += 1) {
      let mixed = 0;
      for (const channel of channels) mixed += channel[i];
      this.sum += mixed / channels.length;
      this.count += 1;
      this.position += 1;
      if (this.position >= this.step) {
        this.position -= this.step;
        this.emit(this.sum / this.count);
        this.sum = 0;
        this.count = 0;
      }
    }
    return true;
  }

  emit(sample) {
    const clipped = Math.max(-1, Math.min(1, sample));
    this.chunk[this.filled] = clipped < 0 ? clipped * 0x8000 : clipped * 0x7fff;
    this.filled += 1;
    if (this.filled === CHUNK_SAMPLES) {
      const full = this.chunk;
      this.port.postMessage(full.buffer, [full.buffer]); // little-endian on every platform we meet
      this.chunk = new Int16Array(CHUNK_SAMPLES);
      this.filled = 0;
    }
  }
}

registerProcessor("pcm16k", Pcm16kProcessor);
