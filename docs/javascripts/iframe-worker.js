/* Search for the site opened from disk (file://).
 *
 * The theme's search runs in a Web Worker, and a page opened from disk may not start one. Here
 * the worker's script runs in a hidden iframe instead, speaking the same messages: what the page
 * posts is dispatched in the iframe as a "message" event, and what the script posts comes back
 * as one on this object. The theme looks for `IFrameWorker` on the page to know that its worker
 * runs in an iframe. Over http(s) nothing changes: the browser's own Worker is used.
 *
 * mkdocs.yml names this file in `extra.polyfills`; the offline plugin then adds no other shim.
 */
(function () {
  "use strict";
  if (location.protocol !== "file:") {
    return;
  }

  class IFrameWorker extends EventTarget {
    constructor(url) {
      super();
      this.queued = []; // messages posted before the script has loaded; null once it has
      this.frame = document.createElement("iframe");
      this.frame.hidden = true;
      document.documentElement.appendChild(this.frame);
      const inner = this.frame.contentWindow;
      inner.postMessage = (data) => this.dispatchEvent(new MessageEvent("message", { data }));
      const script = inner.document.createElement("script");
      script.src = new URL(url, location.href).href;
      script.onload = () => {
        const queued = this.queued;
        this.queued = null;
        queued.forEach((data) => this.deliver(data));
      };
      script.onerror = () => this.dispatchEvent(new Event("error"));
      inner.document.head.appendChild(script);
    }

    deliver(data) {
      const inner = this.frame.contentWindow;
      inner.dispatchEvent(new inner.MessageEvent("message", { data }));
    }

    postMessage(data) {
      if (this.queued === null) {
        this.deliver(data);
      } else {
        this.queued.push(data);
      }
    }

    terminate() {
      this.frame.remove();
    }
  }

  window.IFrameWorker = IFrameWorker;
  window.Worker = IFrameWorker;
})();
