package com.tbp.agent.sim;

import com.tbp.agent.CameraBackend;
import com.tbp.agent.ErrorCode;
import com.tbp.agent.Json;

import java.nio.ByteBuffer;
import java.nio.charset.StandardCharsets;
import java.util.HashMap;
import java.util.LinkedHashMap;
import java.util.Map;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;

/**
 * The simulated phone's camera, in place of Camera2: each call is a CALL frame with a JSON body
 * ({"op": "info" | "focus" | "capture" | "clock", ...}) answered by a REPLY frame
 * ({"ok": true, ...} or {"ok": false, "code", "message"}; a capture's JPEG follows its JSON line).
 * The simulator owns the lens, the sensor clock and the pictures, all on its virtual time.
 */
final class SimCamera implements CameraBackend {

    /** What to do with a REPLY's JSON and the bytes after it. */
    private interface Pending {
        void replied(Map<String, Object> reply, ByteBuffer tail);

        void gone(String why);
    }

    private final SimBus bus;
    private final Map<Integer, Pending> pending = new HashMap<>();
    private int nextCall = 1;
    private boolean gone;
    private Info info;

    SimCamera(SimBus bus) {
        this.bus = bus;
    }

    /** Asks the simulator for the camera's properties (the agent's start waits for them). */
    void open(double exposureS, long iso) throws Exception {
        final Object[] answer = new Object[1];
        final CountDownLatch done = new CountDownLatch(1);
        Map<String, Object> request = new LinkedHashMap<>();
        request.put("op", "info");
        call(request, new Pending() {
            @Override
            public void replied(Map<String, Object> reply, ByteBuffer tail) {
                answer[0] = reply;
                done.countDown();
            }

            @Override
            public void gone(String why) {
                answer[0] = why;
                done.countDown();
            }
        });
        if (!done.await(30, TimeUnit.SECONDS)) {
            throw new Exception("the simulated camera did not describe itself within 30 s");
        }
        if (!(answer[0] instanceof Map)) {
            throw new Exception(String.valueOf(answer[0]));
        }
        @SuppressWarnings("unchecked")
        Map<String, Object> r = (Map<String, Object>) answer[0];
        info = new Info((String) r.get("model"), (String) r.get("serial"), num(r, "min_focus_diopters"),
                (int) num(r, "focus_distance_calibration"), (String) r.get("timestamp_source"),
                exposureS > 0 ? exposureS : num(r, "exposure_s"), iso > 0 ? iso : (long) num(r, "iso"),
                (int) num(r, "image_width"), (int) num(r, "image_height"), num(r, "min_exposure_s"),
                num(r, "max_exposure_s"), (long) num(r, "min_iso"), (long) num(r, "max_iso"));
    }

    private static double num(Map<String, Object> reply, String name) {
        return ((Number) reply.get(name)).doubleValue();
    }

    @Override
    public Info info() {
        return info;
    }

    @Override
    public void focus(double diopters, final Result<Focused> result) {
        Map<String, Object> request = new LinkedHashMap<>();
        request.put("op", "focus");
        request.put("diopters", diopters);
        call(request, new Answering<Focused>(result) {
            @Override
            Focused value(Map<String, Object> reply, ByteBuffer tail) {
                return new Focused(num(reply, "diopters"), ((Number) reply.get("stationary_at_ns")).longValue());
            }
        });
    }

    @Override
    public void capture(double exposureS, long iso, Result<Still> result) {
        Map<String, Object> request = new LinkedHashMap<>();
        request.put("op", "capture");
        request.put("exposure_s", exposureS);
        request.put("iso", iso);
        call(request, new Answering<Still>(result) {
            @Override
            Still value(Map<String, Object> reply, final ByteBuffer tail) {
                return new Still(((Number) reply.get("sensor_timestamp_ns")).longValue(), num(reply, "exposure_s"),
                        num(reply, "focus_diopters")) {
                    @Override
                    public ByteBuffer jpeg() {
                        return tail;
                    }

                    @Override
                    public void release() {
                    }
                };
            }
        });
    }

    @Override
    public void readClock(Result<Long> result) {
        Map<String, Object> request = new LinkedHashMap<>();
        request.put("op", "clock");
        call(request, new Answering<Long>(result) {
            @Override
            Long value(Map<String, Object> reply, ByteBuffer tail) {
                return ((Number) reply.get("device_ns")).longValue();
            }
        });
    }

    @Override
    public void close() {
        bye("the agent closed the camera");
    }

    private void call(Map<String, Object> request, Pending handler) {
        int id;
        synchronized (this) {
            if (gone) {
                handler.gone("the simulated camera is gone");
                return;
            }
            id = nextCall++;
            pending.put(id, handler);
        }
        bus.write(SimBus.CALL, id, Json.write(request).getBytes(StandardCharsets.UTF_8));
    }

    /** A REPLY frame: its JSON line, then (for a capture) the JPEG. */
    void replied(int id, byte[] payload) {
        Pending handler;
        synchronized (this) {
            handler = pending.remove(id);
        }
        if (handler == null) {
            return;
        }
        int newline = 0;
        while (newline < payload.length && payload[newline] != '\n') {
            newline++;
        }
        Map<String, Object> reply;
        try {
            @SuppressWarnings("unchecked")
            Map<String, Object> parsed = (Map<String, Object>) Json.parse(
                    new String(payload, 0, newline, StandardCharsets.UTF_8));
            reply = parsed;
        } catch (Json.SyntaxError | ClassCastException e) {
            handler.gone("the simulated camera answered " + e.getMessage());
            return;
        }
        int start = Math.min(newline + 1, payload.length);
        handler.replied(reply, ByteBuffer.wrap(payload, start, payload.length - start).slice());
    }

    /** The simulator's link closed: every call in flight fails. */
    void bye(String why) {
        Map<Integer, Pending> left;
        synchronized (this) {
            gone = true;
            left = new HashMap<>(pending);
            pending.clear();
        }
        for (Pending handler : left.values()) {
            handler.gone(why);
        }
    }

    /** Turns a REPLY into the backend Result: ok with the value, or the simulator's error code. */
    private abstract static class Answering<T> implements Pending {
        private final Result<T> result;

        Answering(Result<T> result) {
            this.result = result;
        }

        abstract T value(Map<String, Object> reply, ByteBuffer tail);

        @Override
        public void replied(Map<String, Object> reply, ByteBuffer tail) {
            T value = null;
            ErrorCode code = null;
            String message = null;
            try {
                if (Boolean.TRUE.equals(reply.get("ok"))) {
                    value = value(reply, tail);
                } else {
                    code = ErrorCode.valueOf((String) reply.get("code"));
                    message = String.valueOf(reply.get("message"));
                }
            } catch (RuntimeException e) {  // a simulator bug, answered like a HAL error
                code = ErrorCode.CAMERA_ERROR;
                message = "malformed simulated camera reply " + Json.excerpt(reply);
            }
            if (code != null) {
                result.failed(code, message);
            } else {
                result.ok(value);
            }
        }

        @Override
        public void gone(String why) {
            result.failed(ErrorCode.CAMERA_ERROR, why);
        }
    }
}
