"""walkstream's client: follows a tour, keeps streamed representations, draws and measures them.

Modules: ``navigation`` (camera tours), ``cache`` (resident state, GL-free),
``renderer`` (moderngl on EGL, fenced frame timing) and ``app`` (``run_client``:
the websocket session loop). Import what you need from them directly; this
package imports nothing, so ``client.cache`` stays usable without a GL driver.
"""
