package com.tbp.agent;

import java.nio.charset.StandardCharsets;
import java.util.LinkedHashMap;
import java.util.Map;

/** One answer line: {@code {"id": N, "ok": true, ...fields}} or {@code {"id": N, "ok": false, "error": {...}}}. */
public final class Answer {

    /** Error messages are cut to this many characters so an answer line stays far below 64 KiB. */
    public static final int MAX_MESSAGE = 2000;

    private final Map<String, Object> fields = new LinkedHashMap<>();

    private Answer(long id, boolean ok) {
        fields.put("id", id);
        fields.put("ok", ok);
    }

    public static Answer ok(long id) {
        return new Answer(id, true);
    }

    public static Answer error(long id, ErrorCode code, String message) {
        Answer answer = new Answer(id, false);
        String text = message == null ? "" : message;
        if (text.length() > MAX_MESSAGE) {
            text = text.substring(0, MAX_MESSAGE - 3) + "...";
        }
        Map<String, Object> error = new LinkedHashMap<>();
        error.put("code", code.name());
        error.put("message", text);
        answer.fields.put("error", error);
        return answer;
    }

    public static Answer error(long id, AgentError error) {
        return error(id, error.code, error.getMessage());
    }

    public Answer put(String name, Object value) {
        fields.put(name, value);
        return this;
    }

    /** The UTF-8 line, '\n' included. */
    public byte[] line() {
        return (Json.write(fields) + "\n").getBytes(StandardCharsets.UTF_8);
    }

    @Override
    public String toString() {
        return Json.write(fields);
    }
}
